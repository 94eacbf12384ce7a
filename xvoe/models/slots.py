"""Slot pictures and their composite: decoding latents, and where hidden objects stand.

Shared by the MSE surprise (xvoe.evaluation), the explanations and the Pyro scene
(inference.xpl_scene), so that every surprise draws a video the same way.
"""
from __future__ import annotations

import torch
from torch import Tensor

from ..scenes.render import DEPTH_FAR, OBJECT_DEPTH, WALL_DEPTH
from .perception import ComponentVAE

__all__ = ["decode_slots", "composite", "scene_layers", "redraw_slots", "behind_walls", "nearest_wall",
           "push_behind"]


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



def scene_layers(vae: ComponentVAE, refined: Tensor, occupied: Tensor, visible: Tensor,
                 occluder: Tensor) -> tuple[Tensor, Tensor]:
    """The slot pictures (B, T, K, 4, H, W) a video's refined latents draw, and the nearest
    wall's depth (B, T, 1, 1, H, W): a wall is drawn only in the frames in which the encoder saw
    it, and every object it did not see stands behind the walls (`behind_walls`).

    A wall stands in the nearest depth lane, so nothing hides it: unseen, it is out of the
    picture (lowered from above, or lifted away). Transformer 1 fills it there all the same, and
    a fill that draws a wall costs pixels that vary from one video to its partner."""
    return _placed(vae, decode_slots(vae, refined, occupied), visible, occluder)


def redraw_slots(vae: ComponentVAE, layers: Tensor, refined: Tensor, changed: Tensor, visible: Tensor,
                 occluder: Tensor) -> Tensor:
    """The `scene_layers` (B, T, K, 4, H, W) of latents `refined` (B, T, K, D) that differ from
    those `layers` were drawn of only in the `changed` slots (B, K): only those are decoded. The
    kept pictures are placed again, which leaves them as they were while the walls stay: exact
    where no changed slot is a wall."""
    redrawn = torch.where(changed[:, None, :, None, None, None], decode_slots(vae, refined, changed), layers)
    return _placed(vae, redrawn, visible, occluder)[0]


def _placed(vae: ComponentVAE, layers: Tensor, visible: Tensor, occluder: Tensor) -> tuple[Tensor, Tensor]:
    """Decoded slot pictures with the unseen walls out of the picture and every unseen object
    behind the walls, and the walls' `nearest_wall` depth (`scene_layers`)."""
    unseen_walls = (occluder[:, None, :] & ~visible)[..., None, None, None]
    layers = torch.where(unseen_walls, vae.blank()[0], layers)
    walls = nearest_wall(layers, occluder)
    return behind_walls(layers, visible, occluder, walls), walls



_WALL_PIXEL = 0.5    # decoded depth under which a wall's picture covers a pixel ([-1, 1]; walls stand at -0.5)



_BEHIND = 2 * (OBJECT_DEPTH - WALL_DEPTH) / DEPTH_FAR    # from a wall to the objects' lane in [-1, 1]: 0.5



def behind_walls(layers: Tensor, visible: Tensor, occluder: Tensor, walls: Tensor | None = None) -> Tensor:
    """Slot pictures (B, T, K, 4, H, W) in which every object the encoder did not see in a
    frame stands behind the walls there (`push_behind`); seen objects and walls are left
    alone. Transformer 1's fill of a hidden object decodes within a few tenths of the wall's
    depth, and the compositor is soft (a fill 0.2 behind still tints the wall by 6%), so
    without this the fills of objects really behind a wall show through it and cost the
    possible videos pixels; a fill where no wall stands still shows. `walls`: their
    `nearest_wall` depth, if already known (default: from `layers`)."""
    walls = nearest_wall(layers, occluder) if walls is None else walls
    hidden = (~visible & ~occluder[:, None, :])[..., None, None, None]
    return torch.where(hidden, push_behind(layers, walls), layers)



def nearest_wall(layers: Tensor, occluder: Tensor) -> Tensor:
    """Depth (B, T, 1, 1, H, W) of the nearest wall's picture at each pixel (inf: no wall) of
    slot pictures (B, T, K, 4, H, W) whose walls are the slots `occluder` (B, K)."""
    far = torch.full_like(layers[:, :, :1, 3:], float("inf"))
    return torch.where(occluder[:, None, :, None, None, None], layers[:, :, :, 3:], far).amin(dim=2, keepdim=True)



def push_behind(pictures: Tensor, walls: Tensor) -> Tensor:
    """Pictures (..., 4, H, W) whose depth is at least the walls' (..., 1, H, W, broadcast)
    plus BEHIND, the distance from the walls to the objects' lane, where a wall covers the pixel."""
    depth = pictures[..., 3:, :, :]
    pushed = torch.where(walls < _WALL_PIXEL, torch.maximum(depth, walls + _BEHIND), depth)
    return torch.cat([pictures[..., :3, :, :], pushed], dim=-3)
