"""Batches of videos from a latent cache, for the XPL, PLATO and proposal stages.

Every random choice of a step (which videos, the slot order, the slot Transformer 2 must
rebuild, the spans Transformer 1 must refill) is drawn from a generator seeded by (seed, step,
shard), as for perception, so a resumed or multi-process run sees the same batches. What the
cache does not hold (the walls, where the objects are) is read from the split file it was
encoded from.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import XvoeError
from ..scenes import store
from ..scenes.world import WORLD
from .data import focus_on, owned_shards
from .latents import open_latents

__all__ = ["LatentBatch", "LatentBatches", "ProposalBatch", "ProposalBatches", "bridge_hidden", "object_places",
           "outside_picture", "wall_stays"]

_PROPOSAL_OBJECT_SHARE = 0.5   # the proposal stage rebuilds a seen object this often (else any slot); as
                               # in the joint stage: more, and Transformer 2 fills empty slots with objects


@dataclass
class LatentBatch:
    mean: Tensor        # (B, T, K, D)
    visible: Tensor     # (B, T, K) bool
    order: Tensor       # (B, K) slot order
    hidden: Tensor      # (B,) the slot Transformer 2 must rebuild
    refill: Tensor      # (B, T, K) bool: seen entries hidden from Transformer 1, which must rebuild them
    walls: Tensor       # (B, K) bool: the wall slots
    # (B, T, K) bool: entries outside the picture (outside_refill)
    outside: Tensor | None = field(default=None, kw_only=True)

    def to(self, device) -> LatentBatch:
        return replace(self, **{name: value.to(device) for name, value in vars(self).items() if value is not None})

    def __len__(self) -> int:
        return len(self.mean)


class LatentBatches:
    """The shards of a latent cache that one process owns, and its batches of videos."""

    def __init__(self, path: str, *, batch_size: int, shards: int, rank: int = 0, world: int = 1,
                 max_videos: int = 0, seed: int = 0, object_share: float = 0.5, walls: bool = False,
                 outside: bool = False, focus_group: str = "", focus_share: float = 0.0):
        with open_latents(path) as file:
            if file.attrs.get("source_split") == "test":
                raise XvoeError(f"{path} was encoded from a test split; training on impossible events is refused")
            count, frames, slots, dim = file["mean"].shape
            # a video as the model reads it: float32 means (T, K, D) and visibility (T, K)
            owned = owned_shards(path, count, batch_size=batch_size, item_bytes=frames * slots * (4 * dim + 1),
                                 shards=shards, rank=rank, world=world, max_videos=max_videos)
            self.mean = torch.from_numpy(file["mean"][owned.start:owned.stop])            # (N, T, K, D)
            self.visible = torch.from_numpy(file["visible"][owned.start:owned.stop])      # (N, T, K) bool
            source = file.attrs.get("source")       # the split file it was encoded from
        split = _present(source, path, "focus_group") if focus_share and focus_group else path  # read only when used
        self.focus = focus_on(split, owned, focus_group, focus_share)
        found, places = _read_split(source, path, owned.start, owned.stop, walls, outside)
        self.walls = torch.zeros_like(self.visible[:, 0]) if found is None else torch.from_numpy(found)   # (N, K)
        self.outside = None     # (N, T, K) hidden entries wholly outside the picture, where asked for
        if places is not None:
            self.outside = torch.from_numpy(outside_picture(places)) & ~self.visible
        self.shards, self.bounds, self.per_shard = owned.shards, owned.bounds, owned.per_shard
        self.start, self.seed, self.object_share = owned.start, seed, object_share
        self.slots = self.mean.shape[2]

    @property
    def shape(self) -> tuple[int, int, int]:
        """A video's (T, K, D): frames, slots and latent size, which an XPL trained on them is fitted to."""
        return tuple(self.mean.shape[1:])

    def batch(self, step: int) -> LatentBatch:
        video, order, hidden, refill = self.draw(step)
        return LatentBatch(self.mean[video], self.visible[video], order, hidden, refill, self.walls[video],
                           outside=None if self.outside is None else self.outside[video])

    def draw(self, step: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The videos (local indices), slot orders, rebuilt slots and refill spans of a step."""
        videos, orders, hidden, refill = [], [], [], []
        for i, (shard, (start, stop)) in enumerate(zip(self.shards, self.bounds)):
            rng = np.random.default_rng([self.seed, step, shard])
            video = self.focus.draw(rng, i, start, stop, self.per_shard) - self.start
            order = np.argsort(rng.random((self.per_shard, self.slots)), axis=1)
            videos.append(video)
            orders.append(order)
            hidden.append(self.hidden_slots(rng, video, order))
            refill.append(self.refill_spans(rng, len(video)))
        return tuple(torch.from_numpy(np.concatenate(parts)) for parts in (videos, orders, hidden, refill))

    REFILL_SHARE = 0.5   # of the slots, this share has a span of frames hidden from Transformer 1

    def refill_spans(self, rng: np.random.Generator, videos: int) -> np.ndarray:
        """(B, T, K) bool in the original slot order: one span of frames per chosen slot,
        from 1 frame to all but one, anywhere (touching the start or the end, as a wall
        that stands from the start or never lifts hides them)."""
        frames = self.mean.shape[1]
        length = rng.integers(1, frames, (videos, self.slots))
        start = rng.integers(0, frames, (videos, self.slots)) - length // 2
        chosen = rng.random((videos, self.slots)) < self.REFILL_SHARE
        t = np.arange(frames)[None, :, None]
        return (t >= start[:, None]) & (t < (start + length)[:, None]) & chosen[:, None]

    def hidden_slots(self, rng: np.random.Generator, video: np.ndarray, order: np.ndarray) -> np.ndarray:
        """The slot (in the permuted order) Transformer 2 must rebuild in each video.

        Drawn uniformly, most would be empty (8 slots, 2 to 4 objects) and Transformer 2
        learns to propose nothing; so a share `object_share` of the time the slot is drawn
        among the seen objects.
        """
        seen = self.visible[torch.from_numpy(video)].any(dim=1).numpy()         # (B, K), original order
        uniform = rng.integers(0, self.slots, len(video))
        weights = rng.random(seen.shape) * seen
        among_seen = weights.argmax(axis=1)
        use_seen = (rng.random(len(video)) < self.object_share) & seen.any(axis=1)
        original = np.where(use_seen, among_seen, uniform)
        inverse = np.argsort(order, axis=1)                                      # original -> permuted
        return inverse[np.arange(len(video)), original]


@dataclass
class ProposalBatch(LatentBatch):
    # (B, T, K, D) the latents with hidden frames interpolated (`bridge_hidden`)
    target: Tensor | None = field(default=None, kw_only=True)


_STAYS_SHARE = 0.5   # of the videos with a wall that comes and goes, this share is shown one that stays


class ProposalBatches(LatentBatches):
    """The cached means, with walls that stay (`wall_stays`) in a share of the videos, and
    the target: the means with the frames in which a seen object is hidden bridged between
    its seen ones (`bridge_hidden`); the slot to rebuild is drawn among the seen objects
    _PROPOSAL_OBJECT_SHARE of the time."""

    def __init__(self, path: str, **batching: Any):
        super().__init__(path, object_share=_PROPOSAL_OBJECT_SHARE, walls=True, **batching)
        chosen = torch.from_numpy(np.random.default_rng([self.seed, 1]).random(len(self.walls)) < _STAYS_SHARE)
        self.mean, self.visible = wall_stays(self.mean, self.visible, self.walls & chosen[:, None])
        self.target = bridge_hidden(self.mean, self.visible)
        self.empty = _empty_latent(path)

    def batch(self, step: int) -> ProposalBatch:
        video, order, hidden, refill = self.draw(step)
        return ProposalBatch(self.mean[video], self.visible[video], order, hidden, refill, self.walls[video],
                             target=self.target[video])


def _seen_neighbours(visible: Tensor) -> tuple[Tensor, Tensor]:
    """(N, T, K) frame indices: the last frame <= t and the first frame >= t in which each slot
    is seen; where one side has none, the other side's; 0 for a slot seen in no frame."""
    count = visible.shape[1]
    frames = torch.arange(count, device=visible.device).view(1, -1, 1)
    before = torch.where(visible, frames, -1).cummax(dim=1).values
    after = torch.where(visible, frames, count).flip(1).cummin(dim=1).values.flip(1)
    before, after = torch.where(before < 0, after, before), torch.where(after == count, before, after)
    return before.clamp(0, count - 1), after.clamp(0, count - 1)


def _take_frames(mean: Tensor, index: Tensor) -> Tensor:
    """mean (N, T, K, D) at frames index (N, T, K), per video and slot."""
    return torch.gather(mean, 1, index.unsqueeze(-1).expand_as(mean))


def bridge_hidden(mean: Tensor, visible: Tensor) -> Tensor:
    """Latents (N, T, K, D) with each frame in which a seen object is hidden interpolated
    linearly between its nearest seen frames (held at the first or last one beyond them).

    Transformer 2 learns the hidden object in every frame from this. Transformer 1's fills
    would do for the seen frames only: they serve the dynamics, not the truth, and move a
    cube behind a wall next to the ball it stops (docs/decisions.md, "Training
    choices");
    scored on seen frames alone, Transformer 2 proposes nothing in the frames a wall covers.
    A static object is held exactly; one moving behind a wall is bridged at constant speed."""
    before, after = _seen_neighbours(visible)
    frames = torch.arange(mean.shape[1], device=mean.device).view(1, -1, 1)
    share = ((frames - before) / (after - before).clamp_min(1)).unsqueeze(-1).to(mean.dtype)
    bridged = _take_frames(mean, before) * (1 - share) + _take_frames(mean, after) * share
    seen = visible.any(dim=1, keepdim=True)                                           # the others keep theirs
    return torch.where(seen.unsqueeze(-1), bridged, mean)


def _empty_latent(latents: str) -> Tensor:
    """(D,) what the encoder makes of a slot with no pixels (the same for every such slot),
    from the cache's never-present entries; zeros if it holds none."""
    with open_latents(latents) as file:
        mean, present = file["mean"][:200], file["present"][:200]
    empty = mean[~present]
    return torch.from_numpy(empty.mean(0) if len(empty) else np.zeros(mean.shape[-1], np.float32))


def _present(source: str | None, latents: str, needed_by: str) -> str:
    """The split file `source` a latent cache was encoded from; an error naming what needs it if it is gone."""
    if source is None or not Path(source).is_file():
        raise XvoeError(f"{needed_by} needs the split file {source} the cache {latents} was encoded from, "
                        "and it is missing")
    return source


def _read_split(source: str | None, latents: str, start: int, stop: int, walls: bool,
                outside: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
    """What the cache does not hold, read from its split file for videos [start, stop) where asked
    for: the slots that hold a wall (N, K) bool, from the `kind` map (None, with a warning, when
    the file is gone: training goes on as if there were no walls), and `object_places`."""
    found = places = None
    missing = source is None or not Path(source).is_file()
    if walls and missing:
        gone = "records no split file" if source is None else f"was encoded from {source}, which is missing"
        warnings.warn(f"the cache {latents} {gone}: training goes on as if its videos had no walls", stacklevel=2)
    if outside:
        _present(source, latents, "outside_refill")
    if (walls or outside) and not missing:
        with store.open_dataset(source) as file:
            found = store.wall_mask(file, start, stop) if walls else None
            if outside:
                columns = list(file["states"].attrs["state_columns"])
                states = store.read_states(file, start, stop)[..., [columns.index(c) for c in ("x", "y", "size")]]
                states = states * (WORLD / file["rgbd"].shape[2])
                states[..., 1] = WORLD - states[..., 1]
                places = states.astype(np.float32)
    return found, places


def object_places(latents: str, start: int, stop: int) -> np.ndarray:
    """(N, T, K, 3) float32: each slot's centre x, y (up) and size (radius or half side) in world units,
    per frame, from the split file the cache was encoded from."""
    with open_latents(latents) as file:
        source = file.attrs.get("source")
    return _read_split(source, latents, start, stop, walls=False, outside=True)[1]


def outside_picture(places: np.ndarray) -> np.ndarray:
    """(N, T, K) bool: the slots whose object lies wholly outside the picture, from `object_places`
    (size is a ball's radius or a cube's half side: its corners reach size * sqrt(2) from its
    centre, whichever way it turns)."""
    x, y, reach = places[..., 0], places[..., 1], places[..., 2] * np.sqrt(2)
    return (np.minimum(x, y) + reach <= 0) | (np.maximum(x, y) - reach >= WORLD)


def wall_stays(mean: Tensor, visible: Tensor, walls: Tensor) -> tuple[Tensor, Tensor]:
    """Latents of the same videos as if their walls (N, K) stood in every frame: each frame in
    which a wall is unseen takes its latent from the nearest frame in which it is seen.

    Training videos lift their wall at the start and the end, so that what it hides is seen
    then and can be learnt; the hypothetical test videos keep the wall down throughout and
    ask Transformer 2 for an object it never saw. Without this, Transformer 2 answers with
    the wall's training timetable (a wall coming down, then going up)."""
    before, after = _seen_neighbours(visible)
    frames = torch.arange(mean.shape[1], device=mean.device).view(1, -1, 1)
    nearest = torch.where(frames - before <= after - frames, before, after)    # the earlier on a tie
    stays = (walls & visible.any(dim=1)).unsqueeze(1)                           # (N, 1, K)
    return torch.where(stays.unsqueeze(-1), _take_frames(mean, nearest), mean), visible | stays
