"""Surprise of test videos under a trained model: the paper's MSE score, per frame.

    s_img(t) = sum over pixels (frame_t - composite of the decoded refined latents)^2
    s_dyn(t) = sum over pixels (composite of refined latents - composite of the dynamics'
               prediction)^2,  t >= 1, the occluder's slot left out of both composites

Refined latents: Transformer 1 fills the frames in which a seen object is occluded and
Transformer 2 proposes the object seen in no frame. Decoding is the cost, so only occupied
slots are decoded (seen at some frame, or the explained one), the decodes are shared by the
two terms, and videos are scored in batches with no Python loop over frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .models.perception import ComponentVAE
from .models.xpl import XPL


@dataclass
class Surprise:
    s_img: Tensor        # (B, T)
    s_dyn: Tensor        # (B, T); 0 at frame 0
    explained_slot: Tensor   # (B,) the slot Transformer 2 filled, -1 if none

    @property
    def per_frame(self) -> Tensor:
        return self.s_img + self.s_dyn


def decode_slots(vae: ComponentVAE, z: Tensor, occupied: Tensor) -> Tensor:
    """Pictures (B, T, K, 4, H, W) of the latents z (B, T, K, D); unoccupied slots (B, K) are
    left blank (they lose every z-buffer comparison) without running the decoder."""
    batch, frames, slots, _ = z.shape
    blank = vae.blank()[0]
    layers = blank.expand(batch, frames, slots, *blank.shape).clone()
    chosen = occupied[:, None, :].expand(batch, frames, slots)
    if chosen.any():
        layers[chosen] = vae.decode(z[chosen])
    return layers


def composite(vae: ComponentVAE, background: Tensor, layers: Tensor, include: Tensor) -> Tensor:
    """Frames (B, T, 4, H, W) from the background (B, T, 4, H, W) and the slot pictures of
    `include` (B, K) slots; the others are blanked out."""
    blank = vae.blank()[0]
    kept = torch.where(include[:, None, :, None, None, None], layers, blank)
    return vae.composite(torch.cat([background[:, :, None], kept], dim=2))


@torch.no_grad()
def mse_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor,
                 background: Tensor, occluder: Tensor) -> Surprise:
    """frames: (B, T, 4, H, W) in [-1, 1]; mean: (B, T, K, D) posterior means; visible:
    (B, T, K) bool; background: (B, T, D) the background component's means; occluder: (B, K)
    bool, the wall slots."""
    refined = xpl.refine(mean, visible)
    slot = torch.full(mean.shape[:1], -1, dtype=torch.long, device=mean.device)
    if xpl.config.use_reasoning:
        refined, _, slot = xpl.explain(refined, visible)
    occupied = visible.any(dim=1)
    occupied[torch.arange(len(slot))[slot >= 0], slot[slot >= 0]] = True
    batch, frames_count = mean.shape[:2]
    background_pictures = vae.decode(background.flatten(0, 1)).reshape(batch, frames_count, *frames.shape[2:])
    layers = decode_slots(vae, refined, occupied)
    s_img = (frames - composite(vae, background_pictures, layers, occupied)).pow(2).flatten(2).sum(2)

    moving = occupied & ~occluder
    predicted = xpl.dynamics(refined[:, :-1])
    predicted_layers = decode_slots(vae, predicted, moving)
    seen = composite(vae, background_pictures[:, 1:], layers[:, 1:], moving)
    expected = composite(vae, background_pictures[:, 1:], predicted_layers, moving)
    s_dyn = torch.zeros_like(s_img)
    s_dyn[:, 1:] = (seen - expected).pow(2).flatten(2).sum(2)
    return Surprise(s_img, s_dyn, slot)


def aggregate(per_frame: Tensor, how: str) -> Tensor:
    """One score per video from per-frame surprise (B, T): the sum (the paper) or the max."""
    if how == "sum":
        return per_frame.sum(dim=1)
    if how == "max":
        return per_frame.max(dim=1).values
    raise ValueError(f"aggregate must be 'sum' or 'max', not {how!r}")
