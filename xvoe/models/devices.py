"""Where tensors live: the device a user names (`--device`, `device=`), checked before any work,
and mixed precision where the device gains from it.

Networks, batches and encoded videos go to the chosen device; checkpoints hold CPU tensors,
so that one trained anywhere loads anywhere. Networks are initialised and batches drawn on the
CPU before they move, and the SMC's resampling draws from a CPU generator; Pyro's draws (the
NLL's particles) come from the device's own state, seeded from the same seed: a run repeats on
one device, not across devices.
"""
from __future__ import annotations

import contextlib
from typing import Any

import torch

from ..domains import DEVICES
from ..errors import XvoeError

__all__ = ["parse_device", "resolve_device", "device_of", "autocast_dtype", "mixed_precision", "on_cpu"]


def parse_device(name: str | torch.device) -> torch.device:
    """The device `name` names, on this machine or not, or a one-line XvoeError."""
    try:
        found = torch.device(name)
    except (RuntimeError, TypeError):
        raise XvoeError(f"{name!r} is not a device: give {DEVICES}") from None
    if found.type not in ("cpu", "cuda", "mps"):
        raise XvoeError(f"{name!r} is not a device: give {DEVICES}")
    return found


def resolve_device(name: str | torch.device = "cpu") -> torch.device:
    """The device `name` names, or a one-line XvoeError when it is none or this machine lacks it."""
    found = parse_device(name)
    if found.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise XvoeError(f"this machine has no CUDA device for {name!r} (torch {torch.__version__})")
        if found.index is not None and found.index >= count:
            raise XvoeError(f"this machine has no {name!r}: {count} CUDA device(s), numbered from 0")
    elif found.type == "mps" and not torch.backends.mps.is_available():
        raise XvoeError(f"this machine has no MPS device for {name!r}")
    return found


def device_of(module: Any) -> torch.device:
    """The device a network's weights are on; the CPU for anything without weights (a stand-in)."""
    weights = module.parameters() if isinstance(module, torch.nn.Module) else iter(())
    return next((weight.device for weight in weights), torch.device("cpu"))


def autocast_dtype(device: torch.device) -> torch.dtype:
    """The precision networks run in on `device`: bfloat16 on a CUDA device that has it, float32
    elsewhere: on the CPU the casts cost more than the products save (docs/log/decisions-2026-11.md,
    "Not kept: the XPL step in bfloat16")."""
    if device.type == "cuda" and torch.cuda.is_bf16_supported():
        return torch.bfloat16
    return torch.float32


def mixed_precision(device: torch.device) -> contextlib.AbstractContextManager:
    """Autocast to `autocast_dtype` where it is not float32; full precision elsewhere."""
    dtype = autocast_dtype(device)
    return contextlib.nullcontext() if dtype == torch.float32 else torch.autocast(device.type, dtype=dtype)


def on_cpu(value: Any) -> Any:
    """`value` with every tensor in it (in dicts, lists and tuples) moved to the CPU."""
    if isinstance(value, torch.Tensor):
        return value.cpu()
    if isinstance(value, dict):
        return {key: on_cpu(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(on_cpu(item) for item in value)
    return value
