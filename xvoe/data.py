"""Frames of a split file turned into model inputs, and the per-process slices for training.

A training process loads its own contiguous slice of the file into memory once and then
draws every batch from a generator seeded by (seed, step, shard): the batch of a step does
not depend on what ran before, so an interrupted run resumes exactly, and a run split over
N processes sees the same global batch as one process holding all the shards.
"""
from __future__ import annotations

from dataclasses import dataclass

import h5py
import numpy as np
import torch
from torch import Tensor

from . import store
from .errors import XvoeError
from .models.perception import BLANK, PerceptionBatch, normalise

BLANK_SEED = 1 << 20      # the shard number of the blank input's noise (shared by all processes)


def visible_threshold(size: int) -> float:
    """An object counts as visible above this many mask pixels: 4 at 128 px, scaled by area."""
    return 4.0 * (size / 128.0) ** 2


def frame_size(file: h5py.File) -> int:
    return int(file["rgbd"].shape[2])


def check_size(file: h5py.File, image_size: int, what: str = "the model") -> None:
    """Refuse data whose frames are not the size the model was built for."""
    size = frame_size(file)
    if size != image_size:
        raise XvoeError(f"{file.filename} holds {size}x{size} frames but {what} works at "
                        f"{image_size}x{image_size}; generate the data with --size {image_size}")


def masked_inputs(frames: Tensor, ids: Tensor, slots: int) -> dict[str, Tensor]:
    """Cut normalised frames (B,4,H,W) into per-object inputs by the id map (B,H,W).

    Every slot with at least one pixel gives an object image (the frame blanked outside the
    slot's mask); slots without pixels give nothing (they all share the blank input). The
    background input is the frame blanked on the objects, with a mask of its own pixels.
    """
    ids = ids.long()
    counts = torch.nn.functional.one_hot(ids.flatten(1), slots + 1).sum(1)          # (B, K+1)
    frame_index, component = torch.nonzero(counts[:, 1:] > 0, as_tuple=True)
    blank = frames.new_tensor(BLANK).view(1, 4, 1, 1)
    own = ids[frame_index] == (component + 1).view(-1, 1, 1)
    objects = torch.where(own[:, None], frames[frame_index], blank)
    background_mask = (ids == 0)[:, None].to(frames.dtype)
    background = torch.where(background_mask > 0, frames, blank)
    return {"objects": objects, "object_frame": frame_index, "object_slot": component,
            "background": background, "background_mask": background_mask, "pixels": counts[:, 1:]}


def perception_batch(rgbd: np.ndarray | Tensor, ids: np.ndarray | Tensor, slots: int,
                     noise: np.ndarray | Tensor, blank_noise: np.ndarray | Tensor) -> PerceptionBatch:
    """A PerceptionBatch from uint8 frames (B,H,W,4), id maps (B,H,W) and noise (B,K+1,D), (1,D)."""
    frames = normalise(torch.as_tensor(rgbd))
    parts = masked_inputs(frames, torch.as_tensor(ids), slots)
    parts.pop("pixels")
    return PerceptionBatch(frames=frames, **parts, noise=torch.as_tensor(noise, dtype=torch.float32),
                           blank_noise=torch.as_tensor(blank_noise, dtype=torch.float32), slots=slots)


@dataclass
class Slice:
    """Videos [start, stop) of a split file, in memory."""

    rgbd: np.ndarray      # (n, T, H, W, 4) uint8
    ids: np.ndarray       # (n, T, H, W) uint8
    start: int
    stop: int


def load_slice(path: str, start: int, stop: int) -> Slice:
    with store.open_dataset(path) as file:
        return Slice(file["rgbd"][start:stop], file["ids"][start:stop], start, stop)


def shard_bounds(videos: int, shards: int) -> list[tuple[int, int]]:
    """Contiguous video ranges of `shards` near-equal slices."""
    edges = [videos * s // shards for s in range(shards + 1)]
    return list(zip(edges[:-1], edges[1:]))


@dataclass
class Ownership:
    """Which shards of a file one process owns: their ids and video ranges, and how many
    items each shard gives to every step's global batch."""

    shards: list[int]
    bounds: list[tuple[int, int]]
    per_shard: int

    @property
    def start(self) -> int:
        return self.bounds[0][0]

    @property
    def stop(self) -> int:
        return self.bounds[-1][1]


def owned_shards(path: str, videos: int, *, batch_size: int, shards: int, rank: int, world: int,
                 max_videos: int = 0) -> Ownership:
    """Cut `videos` into `shards` slices and give process `rank` of `world` its contiguous run."""
    if shards % world:
        raise XvoeError(f"data_shards {shards} is not a multiple of the {world} processes")
    if batch_size % shards:
        raise XvoeError(f"batch_size {batch_size} is not a multiple of data_shards {shards}")
    videos = min(videos, max_videos) if max_videos else videos
    if videos < shards:
        raise XvoeError(f"{path} holds {videos} videos, fewer than the {shards} data shards")
    per_rank = shards // world
    mine = list(range(rank * per_rank, (rank + 1) * per_rank))
    bounds = shard_bounds(videos, shards)
    return Ownership(mine, [bounds[s] for s in mine], batch_size // shards)


class ShardedFrames:
    """The shards of a split file that one training process owns, and its batches.

    Every step, each of the `shards` slices of the file contributes batch_size/shards frames
    drawn uniformly from its own videos; process `rank` of `world` owns a contiguous run of
    shards and reads only those videos.
    """

    def __init__(self, path: str, *, image_size: int, latent_dim: int, batch_size: int, shards: int,
                 rank: int = 0, world: int = 1, max_videos: int = 0, seed: int = 0):
        with store.open_dataset(path) as file:
            check_size(file, image_size)
            videos = file["rgbd"].shape[0]
            self.slots = int(file["states"].shape[2])
        owned = owned_shards(path, videos, batch_size=batch_size, shards=shards, rank=rank, world=world,
                             max_videos=max_videos)
        self.shards, self.bounds, self.per_shard = owned.shards, owned.bounds, owned.per_shard
        self.data = load_slice(path, owned.start, owned.stop)
        self.latent_dim, self.seed = latent_dim, seed
        self.frames = self.data.rgbd.shape[1]

    def batch(self, step: int) -> PerceptionBatch:
        """The local part of the global batch of `step`; the same whoever asks, whenever."""
        picks, noises = [], []
        for shard, (start, stop) in zip(self.shards, self.bounds):
            rng = np.random.default_rng([self.seed, step, shard])
            video = rng.integers(start, stop, self.per_shard) - self.data.start
            frame = rng.integers(0, self.frames, self.per_shard)
            picks.append((video, frame))
            noises.append(rng.standard_normal((self.per_shard, self.slots + 1, self.latent_dim), dtype=np.float32))
        video = np.concatenate([p[0] for p in picks])
        frame = np.concatenate([p[1] for p in picks])
        blank_noise = np.random.default_rng([self.seed, step, BLANK_SEED]).standard_normal(
            (1, self.latent_dim), dtype=np.float32)
        return perception_batch(self.data.rgbd[video, frame], self.data.ids[video, frame], self.slots,
                                np.concatenate(noises), blank_noise)
