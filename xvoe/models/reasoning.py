"""The reasoning Transformer of XPL: fills in object latents that were not observed.

One class serves twice. Transformer 1 fills the frames in which a seen object is occluded;
Transformer 2 is trained MAE-style on one slot hidden in every frame and, at test, proposes
the object that was never visible: the model's explanation. Tokens are frames x slots of
latents; hidden tokens are replaced by a learned [M] token before the (slot, frame) position
embedding, and observed entries are passed through unchanged:
output = input * keep + prediction * (1 - keep).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..domains import COUNT, POSITIVE, within

__all__ = ["ReasoningConfig", "ReasoningTransformer", "occlusion_keep", "never_seen", "hide_slot",
           "gaussian_nll"]


@dataclass(frozen=True)
class ReasoningConfig:
    latent_dim: int = within(16, COUNT)       # D, as the perception module's
    slots: int = within(8, COUNT)             # K
    frames: int = within(15, COUNT)           # T: the longest video the position table covers
    width: int = within(64, COUNT)            # token width (paper: 256)
    layers: int = within(3, COUNT)            # (paper: 6)
    heads: int = within(4, COUNT)             # (paper: 8)
    mlp: int = within(128, COUNT)             # (paper: 256)
    min_scale: float = within(1e-3, POSITIVE)    # floor of the predicted standard deviation


class ReasoningTransformer(nn.Module):
    """Predicts a mean and a scale for every hidden (keep == False) latent."""

    def __init__(self, config: ReasoningConfig):
        super().__init__()
        self.config = config
        self.embed = nn.Linear(config.latent_dim, config.width)
        self.mask_token = nn.Parameter(torch.zeros(config.width))
        self.position = nn.Parameter(torch.randn(config.frames, config.slots, config.width) * 0.02)
        layer = nn.TransformerEncoderLayer(config.width, config.heads, config.mlp, dropout=0.0,
                                           activation="relu", batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, config.layers, norm=nn.LayerNorm(config.width),
                                             enable_nested_tensor=False)
        self.head = nn.Linear(config.width, 2 * config.latent_dim)

    def forward(self, z: Tensor, keep: Tensor, unread: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """z: (B, T, K, D) latents; keep: (B, T, K) bool, True where z is observed; unread:
        (B, T, K) bool, entries no token attends to (their own outputs then carry nothing).

        Returns the completed latents (observed entries exactly as given) and the predicted
        standard deviation of every entry (0 where observed).
        """
        batch, frames, slots, dim = z.shape
        if frames > self.config.frames or slots != self.config.slots:
            raise ValueError(f"latents of {frames} frames x {slots} slots do not fit a reasoning module "
                             f"built for {self.config.frames} x {self.config.slots}")
        kept = keep.unsqueeze(-1).to(z.dtype)
        tokens = self.embed(z) * kept + self.mask_token * (1 - kept)
        tokens = tokens + self.position[:frames]
        padding = None if unread is None else unread.reshape(batch, frames * slots)
        hidden = self.encoder(tokens.reshape(batch, frames * slots, -1), src_key_padding_mask=padding)
        prediction, raw_scale = self.head(hidden).reshape(batch, frames, slots, 2 * dim).chunk(2, dim=-1)
        mean = z * kept + prediction * (1 - kept)
        scale = (F.softplus(raw_scale) + self.config.min_scale) * (1 - kept)
        return mean, scale


def occlusion_keep(visible: Tensor) -> Tensor:
    """Transformer 1's mask: fill only the frames in which an object seen at some frame is
    hidden; slots never seen (empty, or an object hidden throughout) pass through."""
    seen_somewhere = visible.any(dim=1, keepdim=True)
    return visible | ~seen_somewhere


def never_seen(visible: Tensor) -> Tensor:
    """(B, K) bool: slots visible in no frame."""
    return ~visible.any(dim=1)


def hide_slot(shape: tuple[int, int, int], slot: Tensor) -> Tensor:
    """Transformer 2's mask: every entry kept but slot `slot[b]` of each video, in all frames."""
    batch, frames, slots = shape
    keep = torch.ones(batch, frames, slots, dtype=torch.bool, device=slot.device)
    keep[torch.arange(batch, device=slot.device), :, slot] = False
    return keep


def gaussian_nll(mean: Tensor, scale: Tensor, target: Tensor, where: Tensor, beta: float = 0.0) -> Tensor:
    """Mean negative log-likelihood per hidden latent vector (sum over D) under N(mean, scale).

    beta > 0 weights each entry by scale**(2 beta), held constant (the beta-NLL of Seitzer et
    al., 2022): the plain NLL divides the mean's gradient by scale**2, so an entry that is hard
    early gets a large scale and its mean stops learning. The scale's optimum is unchanged."""
    per_entry = 0.5 * ((target - mean) / scale) ** 2 + torch.log(scale) + 0.5 * torch.log(torch.tensor(2 * torch.pi))
    if beta:
        per_entry = per_entry * scale.detach() ** (2 * beta)
    weights = where.unsqueeze(-1).to(per_entry.dtype)
    return (per_entry * weights).sum() / weights.sum().clamp_min(1.0)
