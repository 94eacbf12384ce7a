"""Multiply-accumulates (MACs) of a step, counted by torch's FlopCounterMode with the operations it
leaves out registered.

FlopCounterMode counts FLOPs (2 per multiply-accumulate of a matrix product or convolution) and
only the operations in its registry. On the CPU two that carry much of our work are missing:
the CPU flash attention (`_aten._scaled_dot_product_flash_attention_for_cpu` and its backward,
what `scaled_dot_product_attention` runs for the ViT, Transformers 1 and 2 and the object
buffer) and the oneDNN LSTM layer (`_aten.mkldnn_rnn_layer` and its backward, what `torch.lstm`
runs for XPL's slot-wise LSTM). `_EXTRA_FORMULAS` counts them from their shapes; elementwise work
(activations, gates, softmax, norms) is counted by neither, as torch counts none.

The same pass counts the bytes each operation reads and writes, to set a step bound by memory
against the machine's bandwidth: the distinct elements of every tensor an aten operation takes
and returns (a broadcast dimension once; an operation that writes into an argument counts it
read and written). Views and bare allocations move nothing. Left out: what a kernel moves inside
itself (a blocked matrix product reads its operands more than once; the flash attention keeps
its scores in cache), and caches, which make a tensor read twice cost less than twice.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from math import prod

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves
from torch.utils.flop_counter import FlopCounterMode, flop_registry

__all__ = ["Operations", "count_operations"]

_aten = torch.ops.aten


def _attention_macs(query: torch.Size, key: torch.Size, value: torch.Size) -> int:
    """Forward: scores Q K^T and their weighted sum of V, over every (query, key) pair; a mask
    does not shorten the CPU kernel's work, so none is subtracted."""
    *batch, queries, width = query
    keys, value_width = key[-2], value[-1]
    return prod(batch) * queries * keys * (width + value_width)


def _attention_backward_macs(query: torch.Size, key: torch.Size, value: torch.Size) -> int:
    """Backward: the flash kernel recomputes the scores from the saved log-sum-exp (Q K^T), then
    forms dP = dO V^T, dV = P^T dO, dQ = dS K and dK = dS^T Q: five products of the forward's size."""
    *batch, queries, width = query
    keys, value_width = key[-2], value[-1]
    return prod(batch) * queries * keys * (3 * width + 2 * value_width)


def _rnn_layer_macs(inputs: torch.Size, weight_ih: torch.Size, weight_hh: torch.Size) -> int:
    """Forward of one recurrent layer: every time step of every sequence multiplies its input by
    W_ih (gates x I) and the previous hidden state by W_hh (gates x L)."""
    steps = prod(inputs) // inputs[-1]
    return steps * (prod(weight_ih) + prod(weight_hh))


def _flops(macs: int) -> int:
    return 2 * macs


def _attention(query, key, value, *args, out_shape=None, **kwargs) -> int:
    return _flops(_attention_macs(query, key, value))


def _attention_backward(grad_out, query, key, value, *args, out_shape=None, **kwargs) -> int:
    return _flops(_attention_backward_macs(query, key, value))


def _rnn_layer(inputs, weight_ih, weight_hh, *args, out_shape=None, **kwargs) -> int:
    return _flops(_rnn_layer_macs(inputs, weight_ih, weight_hh))


def _rnn_layer_backward(inputs, weight_ih, weight_hh, *args, out_shape=None, **kwargs) -> int:
    """Gradients of the inputs and hidden states and of both weights: twice the forward's products
    (the saved workspace holds the gates, nothing is recomputed)."""
    return _flops(2 * _rnn_layer_macs(inputs, weight_ih, weight_hh))


# FLOPs (FlopCounterMode's unit) of the operations its registry lacks, from their argument shapes
_EXTRA_FORMULAS: dict[object, Callable[..., int]] = {
    _aten._scaled_dot_product_flash_attention_for_cpu: _attention,
    _aten._scaled_dot_product_flash_attention_for_cpu_backward: _attention_backward,
    _aten.mkldnn_rnn_layer: _rnn_layer,
    _aten.mkldnn_rnn_layer_backward: _rnn_layer_backward,
}


class _GlobalOnly:
    """Stands in for FlopCounterMode's module tracker: every count goes to "Global". The tracker's
    backward hooks break `torch.autograd.grad` (the NLL's refinement) and per-module sums are unused."""

    parents = frozenset({"Global"})

    def __enter__(self) -> _GlobalOnly:
        return self

    def __exit__(self, *args) -> None:
        return None


# name parts of the operations that multiply-accumulate: products, convolutions, attention, RNNs
_PRODUCT_NAMES = ("mm", "conv", "attention", "rnn", "lstm", "gru", "matmul", "linear", "einsum")


class _Watch(TorchDispatchMode):
    """Notes the operations that look like products yet no formula counts, so that a new kernel
    (another torch, another path) shows as a gap instead of a silently low count."""

    def __init__(self, registry: dict) -> None:
        super().__init__()
        self.registry, self.uncounted = registry, set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func.overloadpacket)
        if func.overloadpacket not in self.registry and any(part in name for part in _PRODUCT_NAMES):
            self.uncounted.add(name)
        return func(*args, **(kwargs or {}))


# operations that only allocate: their output is written by the next operation, counted there
_ALLOCATIONS = frozenset({_aten.empty, _aten.empty_like, _aten.empty_strided, _aten.new_empty, _aten.new_empty_strided})


def _tensor_bytes(tensor: torch.Tensor) -> int:
    """Bytes of the distinct elements a tensor covers: a broadcast (stride 0) dimension once."""
    if tensor.layout != torch.strided:
        return tensor.numel() * tensor.element_size()
    return tensor.element_size() * prod(size for size, stride in zip(tensor.shape, tensor.stride()) if stride)


def _moves_data(func) -> bool:
    """False for a view (its output aliases an input it does not write) and a bare allocation."""
    aliases = (value.alias_info for value in func._schema.returns)
    is_view = any(alias is not None and not alias.is_write for alias in aliases)
    return not is_view and func.overloadpacket not in _ALLOCATIONS


class _Traffic(TorchDispatchMode):
    """Sums the bytes of the tensors each operation reads and writes (module docstring)."""

    def __init__(self) -> None:
        super().__init__()
        self.bytes = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        if _moves_data(func):
            self.bytes += sum(_tensor_bytes(leaf) for leaf in tree_leaves((args, kwargs, out))
                              if isinstance(leaf, torch.Tensor))
        return out


@dataclass(frozen=True)
class Operations:
    """MACs of one run: `macs` all of them, `torch_macs` the part FlopCounterMode counts alone;
    `bytes_moved` what its operations read and write (module docstring)."""

    macs: int
    torch_macs: int
    by_op: dict[str, int]       # MACs per aten operation
    uncounted: frozenset[str]   # operations that look like products but have no formula
    bytes_moved: int = 0

    @property
    def gmacs(self) -> float:
        return self.macs / 1e9

    @property
    def torch_gmacs(self) -> float:
        return self.torch_macs / 1e9

    @property
    def gigabytes(self) -> float:
        return self.bytes_moved / 1e9


def count_operations(step: Callable[[], object]) -> Operations:
    """MACs and bytes moved of one call of `step`, forward and backward. The Transformer's fused
    inference path is switched off while counting: it runs the same products in an op no counter knows."""
    counter = FlopCounterMode(display=False, custom_mapping=_EXTRA_FORMULAS)
    counter.mod_tracker = _GlobalOnly()
    fastpath = torch.backends.mha.get_fastpath_enabled()
    torch.backends.mha.set_fastpath_enabled(False)
    watch, traffic = _Watch(counter.flop_registry), _Traffic()
    try:
        with counter, watch, traffic:     # traffic innermost: it sees each operation before the counter decomposes it
            step()
    finally:
        torch.backends.mha.set_fastpath_enabled(fastpath)
    flops = counter.get_flop_counts().get("Global", {})
    by_op = {str(op): count // 2 for op, count in flops.items()}
    torch_macs = sum(count for op, count in flops.items() if op in flop_registry) // 2
    return Operations(sum(by_op.values()), torch_macs, by_op, frozenset(watch.uncounted), traffic.bytes)
