"""PLATO's InteractionLSTM: predicts every slot's latent at frame t+1 from frames <= t.

Each slot keeps an object buffer of all its past latents, read by attention from its
current state; slot states interact pairwise through an MLP summed over the other slots; a
slot-wise LSTM (shared across slots) carries the history. XPL's form is residual:
z(t+1) = z(t) + f(z(<=t)); PLATO's predicts z(t+1) directly. Slots marked inert (the walls,
which stand in a nearer depth lane and never touch an object) exert no effect on the others.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..domains import COUNT, within

__all__ = ["DynamicsConfig", "DynamicsState", "mlp", "InteractionLSTM"]


@dataclass(frozen=True)
class DynamicsConfig:
    latent_dim: int = within(16, COUNT)       # D
    hidden: int = within(64, COUNT)           # width of the object, buffer and interaction MLPs (paper: 512)
    mlp_layers: int = within(2, COUNT)        # layers of each MLP (paper: 3)
    lstm: int = within(128, COUNT)            # slot-wise LSTM size (paper: 2056)
    buffer_heads: int = within(4, COUNT)      # attention heads that read the object buffer
    residual: bool = True      # XPL: predict the change; PLATO: predict the next latent


class DynamicsState(NamedTuple):
    """What `InteractionLSTM.step` carries from frame to frame."""

    buffer: Tensor      # (B * R, t, H) every stepped slot's object states so far
    hidden: Tensor      # (B * R, L) the slot-wise LSTM's state
    cell: Tensor


def mlp(inputs: int, width: int, layers: int, outputs: int | None = None) -> nn.Sequential:
    sizes = [inputs] + [width] * layers
    modules: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        modules += [nn.Linear(a, b), nn.ReLU()]
    if outputs is not None:
        modules.append(nn.Linear(width, outputs))
    return nn.Sequential(*modules)


class InteractionLSTM(nn.Module):
    def __init__(self, config: DynamicsConfig):
        super().__init__()
        self.config = config
        h = config.hidden
        self.object = mlp(config.latent_dim, h, config.mlp_layers)
        self.buffer = nn.MultiheadAttention(h, config.buffer_heads, batch_first=True)
        # pairwise MLP on [receiver, sender]; its first layer is split into the two halves so
        # that it runs once per slot instead of once per pair
        self.receiver = nn.Linear(h, h)
        self.sender = nn.Linear(h, h, bias=False)
        self.interaction = mlp(h, h, config.mlp_layers - 1)
        self.cell = nn.LSTMCell(3 * h, config.lstm)
        self.out = mlp(config.lstm, h, 1, config.latent_dim)
        nn.init.zeros_(self.out[-1].weight)     # start from "nothing changes" (residual) / zero
        nn.init.zeros_(self.out[-1].bias)

    def forward(self, z: Tensor, inert: Tensor | None = None) -> Tensor:
        """z: (B, T, K, D); inert: (B, K) bool, slots whose effect on the others is left out.
        Returns (B, T, K, D): entry t is the prediction of frame t+1 made from frames 0..t
        (teacher forcing)."""
        batch, frames, slots, _ = z.shape
        state = self.object(z)                                              # (B, T, K, H)
        # object buffer: slot k at frame t attends over its own frames 0..t
        per_slot = state.permute(0, 2, 1, 3).reshape(batch * slots, frames, -1)
        future = torch.triu(torch.ones(frames, frames, dtype=torch.bool, device=z.device), diagonal=1)
        memory, _ = self.buffer(per_slot, per_slot, per_slot, attn_mask=future, need_weights=False)
        memory = memory.reshape(batch, slots, frames, -1).permute(0, 2, 1, 3)
        # pairwise interactions at frame t, summed over the other slots
        pairs = torch.relu(self.receiver(state).unsqueeze(3) + self.sender(state).unsqueeze(2))
        effects = self.interaction(pairs)                                   # (B, T, K, K, H)
        effect = (effects * _senders(slots, inert, z)[:, None, :, :, None]).sum(dim=3)
        inputs = torch.cat([state, memory, effect], dim=-1).reshape(batch, frames, slots, -1)
        outputs = self.recur(inputs.permute(0, 2, 1, 3).reshape(batch * slots, frames, -1))
        change = self.out(outputs).reshape(batch, slots, frames, -1).permute(0, 2, 1, 3)
        return z + change if self.config.residual else change

    def recur(self, inputs: Tensor) -> Tensor:
        """The slot-wise LSTM (`self.cell`) over sequences (N, T, 3H) from a zero state: hidden states
        (N, T, L). One fused call: the input projection of all frames is one matrix product, not one
        per frame (forward and backward 1.6x faster at the paper's sizes)."""
        start = inputs.new_zeros(1, len(inputs), self.config.lstm)
        cell = self.cell
        # torch's own LSTM kernels, not oneDNN's, whose sums follow the CPU (docs/decisions.md, "One
        # seed, one set of weights"); on the CPU they are no slower at these sizes
        with torch.backends.mkldnn.flags(enabled=False, deterministic=None, allow_tf32=None, fp32_precision=None):
            return torch.lstm(inputs, (start, start), [cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh],
                              True, 1, 0.0, self.training, False, True)[0]

    def step(self, z: Tensor, state: DynamicsState | None = None, inert: Tensor | None = None,
             receivers: Tensor | None = None) -> tuple[Tensor, DynamicsState]:
        """One frame at a time: z (B, K, D) is frame t, state what frames < t left. Returns
        the prediction of frame t+1, as `forward` makes it, and the state to carry on; a
        sequential caller (the NLL's particles) pays for each frame once, not once per prefix.

        receivers: the slots (R,) whose prediction is wanted (None: all K), each still moved by
        every slot: a slot's buffer and LSTM feed only its own prediction, so the others' are
        not computed, and the prediction (B, R, D) and the state hold those R slots alone."""
        batch, slots, _ = z.shape
        receivers = slice(None) if receivers is None else receivers
        current = self.object(z)                                            # (B, K, H)
        own_slots = current[:, receivers]                                   # (B, R, H)
        chosen = own_slots.shape[1]
        own = own_slots.reshape(batch * chosen, 1, -1)
        buffer = own if state is None else torch.cat([state.buffer, own], dim=1)
        memory, _ = self.buffer(own, buffer, buffer, need_weights=False)
        pairs = torch.relu(self.receiver(own_slots).unsqueeze(2) + self.sender(current).unsqueeze(1))
        senders = _senders(slots, inert, z)[:, receivers]                   # (1 or B, R, K)
        effect = (self.interaction(pairs) * senders[..., None]).sum(dim=2)
        inputs = torch.cat([own_slots, memory.reshape(batch, chosen, -1), effect], dim=-1).reshape(batch * chosen, -1)
        if state is None:
            hidden = cell = z.new_zeros(batch * chosen, self.config.lstm)
        else:
            hidden, cell = state.hidden, state.cell
        hidden, cell = self.cell(inputs, (hidden, cell))
        change = self.out(hidden).reshape(batch, chosen, -1)
        return (z[:, receivers] + change if self.config.residual else change), DynamicsState(buffer, hidden, cell)

    def rollout(self, z: Tensor, start: int, steps: int) -> Tensor:
        """Predict `steps` frames after frame `start - 1` feeding predictions back in (no teacher)."""
        history = z[:, :start]
        for _ in range(steps):
            history = torch.cat([history, self(history)[:, -1:]], dim=1)
        return history[:, start:]


def _senders(slots: int, inert: Tensor | None, like: Tensor) -> Tensor:
    """(1 or B, K, K) weights of the effect of slot j (last axis) on slot i: 0 on the
    diagonal and from inert slots, 1 elsewhere."""
    others = (1.0 - torch.eye(slots, device=like.device, dtype=like.dtype))[None]
    return others if inert is None else others * (~inert)[:, None, :].to(like.dtype)
