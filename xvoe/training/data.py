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

from ..errors import XvoeError
from ..models.perception import BLANK, PerceptionBatch, normalise
from ..resources import check_memory
from ..scenes import store
from ..scenes.released import SOURCE_NAME
from ..scenes.scenarios import TRAINING_GROUPS
from ..scenes.world import FLOOR, WORLD

__all__ = ["visible_threshold", "check_size", "masked_inputs", "perception_batch", "Ownership",
           "process_counts", "owned_shards", "Focus", "focus_on", "check_focus", "ShardedFrames"]

_BLANK_SEED = 1 << 20      # the shard number of the blank input's noise (shared by all processes)


def visible_threshold(size: int) -> float:
    """An object counts as visible above this many mask pixels: 4 at 128 px, scaled by area."""
    return 4.0 * (size / 128.0) ** 2


def _frame_size(file: h5py.File) -> int:
    return int(file["rgbd"].shape[2])


def check_size(file: h5py.File, image_size: int, what: str = "the model") -> None:
    """Refuse data whose frames are not the size the model was built for."""
    size = _frame_size(file)
    if size != image_size:
        remedy = "import the release again with xvoe import" if file.attrs.get("source") == SOURCE_NAME \
            else "generate the data with"
        raise XvoeError(f"{file.filename} holds {size}x{size} frames but {what} works at "
                        f"{image_size}x{image_size}; {remedy} --size {image_size}")


def masked_inputs(frames: Tensor, ids: Tensor, slots: int) -> dict[str, Tensor]:
    """Cut normalised frames (B,4,H,W) into per-object inputs by the id map (B,H,W).

    Every slot with at least one pixel gives an object image (the frame blanked outside the
    slot's mask; the encoder's input and the target alike); slots without pixels give nothing
    (they all share the blank input).
    The background input is the frame blanked on the objects, with a mask of its own pixels.
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
class _Slice:
    """Videos [start, stop) of a split file, in memory."""

    rgbd: np.ndarray      # (n, T, H, W, 4) uint8
    ids: np.ndarray       # (n, T, H, W) uint8
    start: int
    stop: int


def _load_slice(path: str, start: int, stop: int) -> _Slice:
    with store.open_dataset(path) as file:
        return _Slice(store.read_frames(file, "rgbd", start, stop), store.read_frames(file, "ids", start, stop),
                     start, stop)


def _shard_bounds(videos: int, shards: int) -> list[tuple[int, int]]:
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


def process_counts(shards: int) -> list[int]:
    """The numbers of processes among which `shards` data shards split evenly."""
    return [count for count in range(1, shards + 1) if shards % count == 0]


def owned_shards(path: str, videos: int, *, batch_size: int, item_bytes: int, shards: int, rank: int, world: int,
                 max_videos: int = 0) -> Ownership:
    """Cut `videos` into `shards` slices and give process `rank` of `world` its contiguous run;
    refused before any data is read where a batch of `batch_size` items of `item_bytes` each (as
    the model reads them: a float copy, at the least) is past the machine's free memory."""
    if shards % world:
        fits = ", ".join(map(str, process_counts(shards)))
        raise XvoeError(f"data_shards {shards} is not a multiple of the {world} processes: train in "
                        f"{'one process' if shards == 1 else fits + ' processes'}, or change the batches "
                        f"with --set data_shards=N")
    if batch_size % shards:
        raise XvoeError(f"batch_size {batch_size} is not a multiple of data_shards {shards}")
    check_memory(item_bytes * batch_size, f"--batch-size {batch_size}")
    videos = min(videos, max_videos) if max_videos else videos
    if videos < shards:
        raise XvoeError(f"{path} holds {videos} videos, fewer than the {shards} data shards")
    per_rank = shards // world
    mine = list(range(rank * per_rank, (rank + 1) * per_rank))
    bounds = _shard_bounds(videos, shards)
    return Ownership(mine, [bounds[s] for s in mine], batch_size // shards)


@dataclass
class Focus:
    """A share of each shard's part of a batch drawn from one group's training videos with a
    wall (where a hidden object must be remembered), the rest uniformly from the shard; at
    share 0 the draws are the uniform ones, byte for byte."""

    rows: list[np.ndarray]   # per owned shard: its focus rows (file rows)
    count: int               # how many of the shard's items per batch come from them

    def draw(self, rng: np.random.Generator, index: int, start: int, stop: int, items: int) -> np.ndarray:
        """File rows of `items` videos of owned shard `index` (rows start to stop)."""
        rows = rng.integers(start, stop, items - self.count)
        return np.concatenate([rows, rng.choice(self.rows[index], self.count)]) if self.count else rows


def _share_count(field: str, share: float, per_shard: int, items: str) -> int:
    """How many of the `per_shard` items each shard gives a batch the TrainConfig share `field`
    takes; a share outside [0, 1], or one that rounds to none, is refused."""
    if not 0.0 <= share <= 1.0:
        raise XvoeError(f"{field} must lie in [0, 1], not {share}")
    count = round(per_shard * share)
    if share and not count:
        raise XvoeError(f"{field} {share} of the {per_shard} {items} each shard gives a batch rounds to none")
    return count


def _split_by_shard(path: str, owned: Ownership, found: np.ndarray, rows: np.ndarray, what: str) -> list[np.ndarray]:
    """`found` (one entry per file row of `rows`) split among the owned shards; every shard must
    hold some, `what` naming them in the error."""
    parts = [found[(rows >= start) & (rows < stop)] for start, stop in owned.bounds]
    for (start, stop), part in zip(owned.bounds, parts):
        if not len(part):
            raise XvoeError(f"{path} has no {what} in rows {start} to {stop - 1}")
    return parts


def focus_on(path: str, owned: Ownership, group: str, share: float) -> Focus:
    """The Focus of TrainConfig.focus_group / focus_share for the shards a process owns of the
    training split at `path`."""
    check_focus(group, share)
    count = _share_count("focus_share", share, owned.per_shard, "videos")
    if not count:
        return Focus([], 0)
    with store.open_dataset(path) as file:
        found = _focus_videos(file, group, owned.start, owned.stop)
    return Focus(_split_by_shard(path, owned, found, found, f"{group} videos with a wall"), count)


@dataclass
class _AirborneFrames:
    """TrainConfig.airborne_share for the perception stage. Frames with a ball or cube off the
    floor are a few percent of a split (falling cubes), too few for the encoder and decoder to
    learn to draw an object there."""

    pairs: list[np.ndarray]  # per owned shard: (n, 2) file rows and frames with an object off the floor
    count: int               # how many of the shard's frames per batch come from them


def _airborne_frames_of(path: str, owned: Ownership, share: float) -> _AirborneFrames:
    """The AirborneFrames of `share` for the shards a process owns of the training split at `path`."""
    count = _share_count("airborne_share", share, owned.per_shard, "frames")
    if not count:
        return _AirborneFrames([], 0)
    with store.open_dataset(path) as file:
        found = np.argwhere(_airborne(file, owned.start, owned.stop)) + [owned.start, 0]
    return _AirborneFrames(_split_by_shard(path, owned, found, found[:, 0], "frame with a ball or cube off the floor"),
                          count)


def _airborne(file: h5py.File, start: int, stop: int) -> np.ndarray:
    """(videos, T) bool: frames of rows [start, stop) in which a visible ball or cube's lowest
    point is at least its own half-size above the floor (states are in pixels, y downwards)."""
    columns = list(file["states"].attrs["state_columns"])
    states = store.read_states(file, start, stop)
    y, size = states[..., columns.index("y")], states[..., columns.index("size")]
    kinds = list(file.attrs["kind_names"])
    movable = np.isin(file["kind"][start:stop], [kinds.index("ball"), kinds.index("cube")])[:, None, :]
    floor_row = _frame_size(file) * (1.0 - FLOOR / WORLD)
    lifted = (states[..., columns.index("visible")] > 0) & movable & (y + 2 * size <= floor_row)
    return lifted.any(axis=2)


def check_focus(group: str, share: float | None = None) -> None:
    """A focus_group of training groups only, and one wherever focus_share is set (None: not known
    yet): checked before any data is read or encoded, so that a misspelt or missing group costs no work."""
    for name in (part.strip() for part in group.split(",") if group):
        if name not in TRAINING_GROUPS:
            raise XvoeError(f"focus_group names no group {name!r}; the groups are {', '.join(TRAINING_GROUPS)}")
    if share and not group:      # None (not known yet) is no share
        raise XvoeError("focus_share needs a focus_group (e.g. permanence)")


def _focus_videos(file: h5py.File, group: str, start: int, stop: int) -> np.ndarray:
    """Rows in [start, stop) of a training split's `group` videos that have a wall; `group` may
    name several, comma-separated (permanence,continuity), to hold more than one kind of hidden
    event in each batch."""
    if "group" not in file:
        raise XvoeError("focus_group needs a training split (its `group` labels); this file has none")
    groups = file["group"].asstr()[start:stop]
    present, wanted = set(groups), [name.strip() for name in group.split(",")]
    for name in wanted:
        if name not in present:
            raise XvoeError(f"no training videos of group {name!r}; the groups are {sorted(present)}")
    return start + np.flatnonzero(np.isin(groups, wanted) & file["has_wall"][start:stop].astype(bool))


class ShardedFrames:
    """The shards of a split file that one training process owns, and its batches.

    Every step, each of the `shards` slices of the file contributes batch_size/shards frames
    drawn uniformly from its own videos; process `rank` of `world` owns a contiguous run of
    shards and reads only those videos.
    """

    def __init__(self, path: str, *, image_size: int, latent_dim: int, batch_size: int, shards: int,
                 rank: int = 0, world: int = 1, max_videos: int = 0, seed: int = 0, airborne_share: float = 0.0):
        with store.open_dataset(path, split="train") as file:
            check_size(file, image_size)
            videos = file["rgbd"].shape[0]
            self.slots = int(file["states"].shape[2])
        # a frame as the model reads it: RGBD floats
        owned = owned_shards(path, videos, batch_size=batch_size, item_bytes=4 * 4 * image_size ** 2, shards=shards,
                             rank=rank, world=world, max_videos=max_videos)
        self.shards, self.bounds, self.per_shard = owned.shards, owned.bounds, owned.per_shard
        self.data = _load_slice(path, owned.start, owned.stop)
        self.latent_dim, self.seed = latent_dim, seed
        self.frames = self.data.rgbd.shape[1]
        self.airborne = _airborne_frames_of(path, owned, airborne_share)

    def batch(self, step: int) -> PerceptionBatch:
        """The local part of the global batch of `step`; the same whoever asks, whenever."""
        video, frame, noise = self._draw(step)
        video -= self.data.start
        blank_noise = np.random.default_rng([self.seed, step, _BLANK_SEED]).standard_normal(
            (1, self.latent_dim), dtype=np.float32)
        return perception_batch(self.data.rgbd[video, frame], self.data.ids[video, frame], self.slots,
                                noise, blank_noise)

    def picks(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """The file rows and frames of the local part of `step`'s batch, in batch order."""
        return self._draw(step)[:2]

    def _draw(self, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """File rows, frames and reparameterisation noise of `step`, shard by shard."""
        videos, frames, noises = [], [], []
        for index, (shard, (start, stop)) in enumerate(zip(self.shards, self.bounds)):
            rng = np.random.default_rng([self.seed, step, shard])
            uniform = self.per_shard - self.airborne.count
            videos.append(rng.integers(start, stop, uniform))
            frames.append(rng.integers(0, self.frames, uniform))
            if self.airborne.count:
                lifted = rng.choice(self.airborne.pairs[index], self.airborne.count)
                videos[-1], frames[-1] = (np.concatenate([videos[-1], lifted[:, 0]]),
                                          np.concatenate([frames[-1], lifted[:, 1]]))
            noises.append(rng.standard_normal((self.per_shard, self.slots + 1, self.latent_dim), dtype=np.float32))
        return np.concatenate(videos), np.concatenate(frames), np.concatenate(noises)
