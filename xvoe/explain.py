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
from .data import check_size, visible_threshold
from .errors import XvoeError
from .latents import encode_frames
from .models.perception import to_uint8
from .score import Scorer, composite, decode_slots
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
        rgbd, ids, kind = file["rgbd"][index], file["ids"][index], file["kind"][index]
        frames, size, slots = rgbd.shape[0], rgbd.shape[1], file["states"].shape[2]
        walls = [list(file.attrs["kind_names"]).index(k) for k in ("wall", "window_wall")]
        title = describe(file, index)
    encoded = encode_frames(scorer.vae, rgbd, ids, slots)
    mean = torch.from_numpy(encoded["mean"])[None]
    visible = torch.from_numpy(encoded["pixels"] > visible_threshold(size))[None]
    background = torch.from_numpy(encoded["background_mean"])[None]
    refined = scorer.xpl.refine(mean, visible)
    slot = torch.tensor([-1])
    if scorer.xpl.config.use_reasoning:
        refined, _, slot = scorer.xpl.explain(refined, visible)
    occupied = visible.any(1)
    if slot[0] >= 0:
        occupied[0, slot[0]] = True
    occluder = torch.from_numpy(np.isin(kind, walls))[None]
    layers = decode_slots(scorer.vae, refined, occupied)
    background_pictures = scorer.vae.decode(background[0])[None]
    behind = composite(scorer.vae, background_pictures, layers, occupied & ~occluder)
    if slot[0] >= 0:
        alone = layers[0, :, slot[0]]
    else:
        alone = scorer.vae.blank()[0].expand(frames, *layers.shape[-3:])
    return Explanation(rgbd, to_uint8(behind[0]).numpy(), to_uint8(alone).numpy(), int(slot[0]), title)
