"""What the model believes is behind the wall: decoded refined latents of one video.

For each frame: the observed frame; the decoded scene with the occluder's slot left out
(Transformer 1's filled-in objects and Transformer 2's explanation, seen through the wall);
and the explanation object alone (the never-visible slot Transformer 2 proposed).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from . import store
from .data import check_size
from .errors import XvoeError
from .models.perception import to_uint8
from .score import Scorer, composite, decode_slots, encode_videos, explained_latents
from .viz import describe


@dataclass
class Explanation:
    observed: np.ndarray        # (T, H, W, 4) uint8
    behind_wall: np.ndarray     # (T, H, W, 4) uint8: the scene without the occluder
    hidden_object: np.ndarray   # (T, H, W, 4) uint8: the explanation alone, on the blank
    slot: int                   # the explained slot, -1 if every slot was seen
    title: str


@torch.no_grad()
def explain(scorer: Scorer, data: str, index: int) -> Explanation:
    if scorer.is_random:
        raise XvoeError("the random agent explains nothing; give a trained model")
    with store.open_dataset(data) as file:
        count = file["rgbd"].shape[0]
        if not 0 <= index < count:
            raise XvoeError(f"index {index} is out of range: the file holds videos 0..{count - 1}")
        check_size(file, scorer.vae.config.image_size, f"the model {scorer.name}")
        video = encode_videos(scorer, file, index, index + 1)
        rgbd, frames = file["rgbd"][index], file["rgbd"].shape[1]
        title = describe(file, index)
    refined, slot, occupied = explained_latents(scorer.xpl, video["mean"], video["visible"])
    occluder = video["occluder"]
    layers = decode_slots(scorer.vae, refined, occupied)
    background_pictures = scorer.vae.decode(video["background"][0])[None]
    behind = composite(scorer.vae, background_pictures, layers, occupied & ~occluder)
    if slot[0] >= 0:
        alone = layers[0, :, slot[0]]
    else:
        alone = scorer.vae.blank()[0].expand(frames, *layers.shape[-3:])
    return Explanation(rgbd, to_uint8(behind[0]).numpy(), to_uint8(alone).numpy(), int(slot[0]), title)


# --- measuring explanations against the ground truth --------------------------------------

OBJECT_DEPTH_LIMIT = 0.75   # normalised depth: decoded objects lie near 0, the blank at 1.5


def silhouette(states: np.ndarray, columns: list[str], kind: str, size: int) -> np.ndarray:
    """The whole silhouette (T, H, W) of one object from its saved states (T, S), occlusion
    ignored: a disk for a ball, a square for a cube."""
    x, y, half = (states[:, columns.index(c)] for c in ("x", "y", "size"))
    centres = np.arange(size) + 0.5
    dx = centres[None, None, :] - x[:, None, None]
    dy = centres[None, :, None] - y[:, None, None]
    if kind == "ball":
        mask = dx ** 2 + dy ** 2 <= half[:, None, None] ** 2
    else:
        mask = (np.abs(dx) <= half[:, None, None]) & (np.abs(dy) <= half[:, None, None])
    return mask & (states[:, columns.index("present")] > 0)[:, None, None]


def decoded_mask(pictures: np.ndarray | torch.Tensor) -> np.ndarray:
    """Where a decoded object (..., 4, H, W), in normalised units, draws something."""
    depth = torch.as_tensor(pictures)[..., 3, :, :]
    return (depth < OBJECT_DEPTH_LIMIT).numpy()


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks; 1 when both are empty."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
