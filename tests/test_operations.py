"""The operation counter against hand counts from each layer's shapes (multiply-accumulates)."""
from __future__ import annotations

import torch
from torch import nn

from xvoe.evaluation.operations import count_operations


def forward_backward(module: nn.Module, inputs: torch.Tensor):
    """A training step's arithmetic: the forward, then the backward through weights and inputs."""
    inputs = inputs.requires_grad_()
    return lambda: module(inputs).sum().backward()


def test_linear_forward_and_backward():
    layer, x = nn.Linear(24, 40), torch.randn(6, 24)
    forward = 6 * 24 * 40
    assert count_operations(lambda: layer(x)).macs == forward
    # backward: the input's gradient and the weight's, each the size of the forward
    assert count_operations(forward_backward(layer, x)).macs == 3 * forward


def test_conv2d_counts_every_output_pixel():
    layer, x = nn.Conv2d(4, 8, 5, stride=2, padding=2), torch.randn(2, 4, 16, 16)
    forward = 2 * 8 * 8 * 8 * (4 * 5 * 5)          # N * H_out * W_out * C_out * (C_in * k * k)
    assert count_operations(lambda: layer(x)).macs == forward
    assert count_operations(forward_backward(layer, x)).macs == 3 * forward


def test_conv_transpose2d_counts_every_input_pixel():
    layer, x = nn.ConvTranspose2d(8, 4, 4, stride=2, padding=1), torch.randn(2, 8, 8, 8)
    forward = 2 * 8 * 8 * 8 * (4 * 4 * 4)          # N * H_in * W_in * C_in * (C_out * k * k)
    assert count_operations(lambda: layer(x)).macs == forward
    assert count_operations(forward_backward(layer, x)).macs == 3 * forward


def transformer_layer_macs(batch: int, tokens: int, width: int, mlp: int) -> tuple[int, int, int]:
    """(linear products, attention forward, attention backward) of one encoder layer, by hand."""
    rows = batch * tokens
    linears = rows * width * 3 * width + rows * width * width + 2 * rows * width * mlp   # Q, K, V; out; MLP
    attention = batch * tokens * tokens * width * 2          # Q K^T and P V over all heads
    return linears, attention, attention * 5 // 2            # backward: scores recomputed, then 4 products


def test_transformer_encoder_layer_counts_the_cpu_flash_attention():
    layer = nn.TransformerEncoderLayer(32, 4, 48, dropout=0.0, batch_first=True, norm_first=True)
    x = torch.randn(3, 10, 32)
    linears, attention, attention_backward = transformer_layer_macs(3, 10, 32, 48)
    forward = count_operations(lambda: layer(x))
    assert forward.macs == linears + attention
    assert forward.torch_macs == linears                     # what torch alone leaves out
    assert count_operations(forward_backward(layer, x)).macs == 3 * linears + attention + attention_backward


def test_transformer_inference_path_counted_like_training():
    layer = nn.TransformerEncoderLayer(32, 4, 48, dropout=0.0, batch_first=True).eval()
    linears, attention, _ = transformer_layer_macs(3, 10, 32, 48)
    with torch.no_grad():
        assert count_operations(lambda: layer(torch.randn(3, 10, 32))).macs == linears + attention


def test_lstm_layer_forward_and_backward():
    inputs, hidden, sequences, steps = 12, 20, 5, 7
    lstm, x = nn.LSTM(inputs, hidden, batch_first=True), torch.randn(sequences, steps, inputs)
    forward = sequences * steps * 4 * hidden * (inputs + hidden)     # four gates from x_t and h_{t-1}
    found = count_operations(lambda: lstm(x))
    assert found.macs == forward
    assert found.torch_macs == 0                               # the fused layer is invisible to torch
    # backward: the gradients of inputs, hidden states, W_ih and W_hh
    assert count_operations(lambda: lstm(x.requires_grad_())[0].sum().backward()).macs == 3 * forward


def test_lstm_cell_forward():
    cell, x = nn.LSTMCell(12, 20), torch.randn(5, 12)
    assert count_operations(lambda: cell(x)).macs == 5 * 4 * 20 * (12 + 20)


def test_counts_through_autograd_grad():
    # the NLL's refinement takes gradients with torch.autograd.grad, which module hooks would break
    layer, x = nn.Linear(24, 40), torch.randn(6, 24, requires_grad=True)
    assert count_operations(lambda: torch.autograd.grad(layer(x).sum(), x)).macs == 2 * 6 * 24 * 40


def test_a_product_without_formula_is_named():
    # the Transformer's fused inference kernel, called directly, runs products no formula counts
    width, heads, x = 32, 4, torch.randn(3, 10, 32)
    qkv, proj = nn.Linear(width, 3 * width), nn.Linear(width, width)
    with torch.no_grad():
        found = count_operations(lambda: torch._native_multi_head_attention(
            x, x, x, width, heads, qkv.weight, qkv.bias, proj.weight, proj.bias, need_weights=False))
    assert found.uncounted == {"aten._native_multi_head_attention"}
    assert found.macs == 0


def test_linear_bytes_are_its_operands_and_output():
    layer, x = nn.Linear(24, 40), torch.randn(6, 24)
    # addmm reads the bias, the input and the weight (its transpose is a view) and writes the output
    assert count_operations(lambda: layer(x)).bytes_moved == 4 * (40 + 6 * 24 + 24 * 40 + 6 * 40)


def test_views_move_nothing_and_in_place_reads_and_writes():
    x = torch.randn(100, 50)
    assert count_operations(lambda: x.t().reshape(50, 100)).bytes_moved == 0
    assert count_operations(lambda: x.mul_(2.0)).bytes_moved == 2 * 4 * 100 * 50


def test_a_broadcast_operand_is_read_once():
    x, row = torch.randn(100, 50), torch.randn(1, 50)
    assert count_operations(lambda: x + row.expand(100, 50)).bytes_moved == 4 * (100 * 50 + 50 + 100 * 50)
