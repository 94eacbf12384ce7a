"""The XPL and PLATO training stages, on the latent cache, through the shared loop.

`xvoe train xpl` trains Transformer 1 and the dynamics jointly on the dynamics loss
and Transformer 2 on Transformer 1's refined latents; `xvoe train plato` trains the dynamics
alone (no residual) on the raw means; `--no-residual` gives the paper's ablation (Fig. 5a).
Every random choice of a step (which videos, the slot order, the slot Transformer 2 must
rebuild) is drawn from a generator seeded by (seed, step, shard), as for perception, so a
resumed or multi-process run sees the same batches.
"""
from __future__ import annotations

import hashlib
import os
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ..errors import XvoeError
from ..models.config import from_dict, override, override_resumed, to_dict
from ..models.devices import resolve_device
from ..models.nll import InferenceConfig
from ..models.reasoning import hide_slot
from ..models.xpl import XPL, XPLConfig, permute_slots
from ..scenes import store
from ..scenes.world import WORLD
from .checkpoints import load_checkpoint, load_weights, recorded_input, resolve_run
from .config import TrainConfig
from .data import focus_on, owned_shards
from .latents import check_cache, encode_split, encoder_key, open_latents, split_cache
from .loop import Job, checkpoint_path, fit, setup_distributed, start_process
from .perception import load_perception
from .recipes import DEFAULT_RECIPE, recipe, recipe_of
from .stages import STAGES

# the stages this module trains from the latent cache alone (the proposal stage builds on xpl.pt)
TRAINED_ON_LATENTS = tuple(name for name, entry in STAGES.items() if entry.variant and entry.reads == "latents")

PROPOSAL_OBJECT_SHARE = 0.5   # the proposal stage rebuilds a seen object this often (else any slot); as
                              # in the joint stage: more, and Transformer 2 fills empty slots with objects
PROPOSAL_BETA = 0.5   # the proposal stage's loss is the beta-NLL: with the plain NLL a hard latent's scale
                      # grows and its mean stops learning (docs/decisions.md, "Proposal loss: beta-NLL")


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
            owned = owned_shards(path, file["mean"].shape[0], batch_size=batch_size, shards=shards, rank=rank,
                                 world=world, max_videos=max_videos)
            self.mean = torch.from_numpy(file["mean"][owned.start:owned.stop])
            self.visible = torch.from_numpy(file["visible"][owned.start:owned.stop])
        split = source_split(path, "focus_group") if focus_share and focus_group else path   # read only when used
        self.focus = focus_on(split, owned, focus_group, focus_share)
        found = wall_slots(path, owned.start, owned.stop) if walls else None    # (read only when used)
        self.walls = torch.zeros_like(self.visible[:, 0]) if found is None else torch.from_numpy(found)
        self.outside = None     # (B, T, K) hidden entries wholly outside the picture, where asked for
        if outside:
            places = object_places(path, owned.start, owned.stop)
            self.outside = torch.from_numpy(outside_picture(places)) & ~self.visible
        self.shards, self.bounds, self.per_shard = owned.shards, owned.bounds, owned.per_shard
        self.start, self.seed, self.object_share = owned.start, seed, object_share
        self.slots = self.mean.shape[2]

    @property
    def item_bytes(self) -> int:
        """Bytes of one video's latents and visibility in a batch."""
        return int(self.mean[:1].nbytes + self.visible[:1].nbytes)

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


def stage_config(base: XPLConfig, name: str, stop_gradient: bool, shape: tuple) -> XPLConfig:
    """The recipe's XPL config fitted to the cache's (T, K, D) and to the stage's variant."""
    frames, slots, dim = shape
    entry = STAGES[name]
    reasoning = replace(base.reasoning, latent_dim=dim, slots=slots, frames=max(frames, base.reasoning.frames))
    dynamics = replace(base.dynamics, latent_dim=dim, residual=entry.residual)
    return replace(base, reasoning=reasoning, dynamics=dynamics, use_reasoning=entry.variant == "xpl",
                   stop_target_gradient=stop_gradient)


def train_xpl(latents: str | os.PathLike | None, run_dir: str | os.PathLike, *, stage: str = "xpl",
              recipe_name: str = DEFAULT_RECIPE, stop_gradient: bool = True,
              resume: bool = False, overwrite: bool = False, progress: bool = True, model_overrides: dict | None = None,
              device: str = "cpu", **train_overrides: Any) -> Path:
    """What `xvoe train xpl|plato|xpl-noresidual` does (also under torchrun, on `device`), into RUN_DIR/STAGE.pt.
    `model_overrides` change XPLConfig fields of a fresh run (dotted names reach nested
    configs); a resumed run keeps its network."""
    if stage not in TRAINED_ON_LATENTS:
        raise XvoeError(f"stage must be one of {', '.join(TRAINED_ON_LATENTS)}, not {stage!r}")
    place = setup_distributed(device)
    run_dir = Path(run_dir)
    ckpt = checkpoint_path(run_dir, stage)
    if resume and ckpt.exists():
        state = load_checkpoint(ckpt, stage)
        model_config = from_dict(XPLConfig, state["config"]["xpl"])
        config, recipe_name = from_dict(TrainConfig, state["train"]), recipe_of(state["config"])
        latents = latents or recorded_input(state, ckpt, "latents")
        model_config = override_resumed(model_config, model_overrides, what=f"{stage} run")
    elif latents is None:
        raise XvoeError(f"nothing to resume in {run_dir}: give the latent cache to start a run")
    else:
        chosen = recipe(recipe_name)
        with open_latents(latents) as file:
            shape = file["mean"].shape[1:]
            if file.attrs.get("source_split") == "test":
                raise XvoeError(f"{latents} was encoded from a test split; training on impossible events is refused")
        model_config = override(stage_config(chosen.xpl, stage, stop_gradient, shape),
                                **(model_overrides or {}))
        config = chosen.training(stage)
    config = override(config, **train_overrides)
    config = start_process(config, place)
    needs_walls = model_config.inert_walls or model_config.refill_ignores_walls
    batches = LatentBatches(str(latents), batch_size=config.batch_size, shards=config.data_shards, rank=place.rank,
                            world=place.world, max_videos=config.max_videos, seed=config.seed, walls=needs_walls,
                            outside=model_config.outside_refill,
                            focus_group=config.focus_group, focus_share=config.focus_share)
    model = XPL(model_config)
    if model_config.use_reasoning and not model_config.joint_proposal:
        # trained by the proposal stage; frozen here, so that DistributedDataParallel expects no gradient
        for part in (model.transformer2, model.existence):
            part.requires_grad_(False)
    stored = {"recipe": recipe_name, "xpl": to_dict(model_config)}
    if stage == "xpl":      # the model the NLL surprise runs on keeps its recipe's settings of it
        resumed = nll_settings_of(state["config"]) if resume and ckpt.exists() else None
        stored["nll"] = to_dict(resumed or recipe(recipe_name).nll)
    job = Job(stage, model, batches.batch, stored, meta={"latents": str(Path(latents).resolve())},
              item_bytes=batches.item_bytes)
    return fit(job, config, run_dir, place=place, resume=resume, overwrite=overwrite, progress=progress)


def nll_settings_of(config: dict) -> InferenceConfig | None:
    """The NLL settings an xpl checkpoint's config stores; None where it stores none (made before
    they were stored: a score then takes InferenceConfig's defaults and says so)."""
    return from_dict(InferenceConfig, config["nll"]) if "nll" in config else None


def latent_cache_for(data: str | os.PathLike, run_dir: str | os.PathLike, perception: str | None = None,
                     progress: bool = True, device: str = "cpu") -> Path:
    """The latent cache to train on: `data` itself if it is one; for a split file, the cache
    RUN_DIR/latents-NAME.h5, encoded first (on `device`) with the run's perception module if missing."""
    data = Path(data)
    try:
        open_latents(data).close()
        return data
    except XvoeError:
        pass
    cache = default_cache(data, run_dir)
    if cache.exists():
        check_cache(cache, data)
    else:
        with store.open_dataset(data, split="train"):
            pass
        encode_split(perception or run_dir, data, cache, progress=progress, device=device)
    return cache


def default_cache(data: str | os.PathLike, run_dir: str | os.PathLike) -> Path:
    """Where a run keeps the latent cache of the split `data`: RUN_DIR/latents-NAME.h5."""
    return Path(run_dir) / f"latents-{Path(data).stem}.h5"


def encoded_cache(data: str | os.PathLike, run_dir: str | os.PathLike, perception: str | None = None,
                  device: str = "cpu") -> Path:
    """Where `xvoe encode` writes the latent cache of the split `data` by default: a training
    split's in the run (`default_cache`); a test split's beside it (`split_cache` of the
    perception module, `perception` or the run's, encoding on `device`), where every score of
    that perception reads it."""
    with store.open_hdf5(data) as file:
        kind = file.attrs.get("split")
    if kind != "test":
        return default_cache(data, run_dir)
    return split_cache(data, encoder_key(load_perception(perception or run_dir)[0], resolve_device(device)))


@dataclass
class ProposalBatch(LatentBatch):
    # (B, T, K, D) the latents with hidden frames interpolated (`bridge_hidden`)
    target: Tensor | None = field(default=None, kw_only=True)


STAYS_SHARE = 0.5   # of the videos with a wall that comes and goes, this share is shown one that stays


class ProposalBatches(LatentBatches):
    """The cached means, with walls that stay (`wall_stays`) in a share of the videos, and
    the target: the means with the frames in which a seen object is hidden bridged between
    its seen ones (`bridge_hidden`); the slot to rebuild is drawn among the seen objects
    PROPOSAL_OBJECT_SHARE of the time."""

    def __init__(self, path: str, **batching: Any):
        super().__init__(path, object_share=PROPOSAL_OBJECT_SHARE, walls=True, **batching)
        chosen = torch.from_numpy(np.random.default_rng([self.seed, 1]).random(len(self.walls)) < STAYS_SHARE)
        self.mean, self.visible = wall_stays(self.mean, self.visible, self.walls & chosen[:, None])
        self.target = bridge_hidden(self.mean, self.visible)
        self.empty = empty_latent(path)

    def batch(self, step: int) -> ProposalBatch:
        video, order, hidden, refill = self.draw(step)
        return ProposalBatch(self.mean[video], self.visible[video], order, hidden, refill, self.walls[video],
                             target=self.target[video])


def seen_neighbours(visible: Tensor) -> tuple[Tensor, Tensor]:
    """(N, T, K) frame indices: the last frame <= t and the first frame >= t in which each slot
    is seen; where one side has none, the other side's; 0 for a slot seen in no frame."""
    count = visible.shape[1]
    frames = torch.arange(count, device=visible.device).view(1, -1, 1)
    before = torch.where(visible, frames, -1).cummax(dim=1).values
    after = torch.where(visible, frames, count).flip(1).cummin(dim=1).values.flip(1)
    before, after = torch.where(before < 0, after, before), torch.where(after == count, before, after)
    return before.clamp(0, count - 1), after.clamp(0, count - 1)


def take_frames(mean: Tensor, index: Tensor) -> Tensor:
    """mean (N, T, K, D) at frames index (N, T, K), per video and slot."""
    return torch.gather(mean, 1, index.unsqueeze(-1).expand_as(mean))


def bridge_hidden(mean: Tensor, visible: Tensor) -> Tensor:
    """Latents (N, T, K, D) with each frame in which a seen object is hidden interpolated
    linearly between its nearest seen frames (held at the first or last one beyond them).

    Transformer 2 learns the hidden object in every frame from this. Transformer 1's fills
    would do for the seen frames only: they serve the dynamics, not the truth, and move a
    cube behind a wall next to the ball it stops (docs/decisions.md, "Proposal targets bridge the
    hidden spans");
    scored on seen frames alone, Transformer 2 proposes nothing in the frames a wall covers.
    A static object is held exactly; one moving behind a wall is bridged at constant speed."""
    before, after = seen_neighbours(visible)
    frames = torch.arange(mean.shape[1], device=mean.device).view(1, -1, 1)
    share = ((frames - before) / (after - before).clamp_min(1)).unsqueeze(-1).to(mean.dtype)
    bridged = take_frames(mean, before) * (1 - share) + take_frames(mean, after) * share
    seen = visible.any(dim=1, keepdim=True)                                           # the others keep theirs
    return torch.where(seen.unsqueeze(-1), bridged, mean)


def empty_latent(latents: str) -> Tensor:
    """(D,) what the encoder makes of a slot with no pixels (the same for every such slot),
    from the cache's never-present entries; zeros if it holds none."""
    with open_latents(latents) as file:
        mean, present = file["mean"][:200], file["present"][:200]
    empty = mean[~present]
    return torch.from_numpy(empty.mean(0) if len(empty) else np.zeros(mean.shape[-1], np.float32))


class ProposalNetworks(nn.Module):
    """What the proposal stage trains: Transformer 2 and the existence head of a trained XPL,
    registered under the XPL's own names (so the stage's checkpoint overlays xpl.pt), while
    Transformer 1 and the dynamics stay frozen outside it.

    Transformer 2 sees the other slots as Transformer 1 refines them with the rebuilt slot
    emptied, as at test, where the hidden object was never seen: refined with the object in
    view, a partly occluded ball's fill carries where the object stands, a clue that is gone
    at test."""

    def __init__(self, xpl: XPL, empty: Tensor):
        super().__init__()
        self.transformer2, self.existence = xpl.transformer2, xpl.existence
        self.refine, self.losses = xpl.refine, xpl.proposal_losses
        self.register_buffer("empty", empty, persistent=False)

    def forward(self, batch: ProposalBatch) -> dict[str, Tensor]:
        walls = batch.walls.unsqueeze(1).expand_as(batch.visible)
        raw, visible, target, walls = permute_slots(batch.mean, batch.visible, batch.target, walls, order=batch.order)
        rebuilt = ~hide_slot(visible.shape, batch.hidden)
        with torch.no_grad():
            context = self.refine(torch.where(rebuilt.unsqueeze(-1), self.empty, raw), visible & ~rebuilt, walls[:, 0])
        out = self.losses(torch.where(rebuilt.unsqueeze(-1), target, context), visible, batch.hidden, PROPOSAL_BETA)
        out["loss"] = out["mae"] + out["existence"]
        return out


def cache_source(latents: str) -> str | None:
    """The split file a latent cache was encoded from, as the cache records it."""
    with open_latents(latents) as file:
        return file.attrs.get("source")


def source_split(latents: str, needed_by: str) -> str:
    """The split file a latent cache was encoded from; an error naming what needs it if it is gone."""
    source = cache_source(latents)
    if source is None or not Path(source).is_file():
        raise XvoeError(f"{needed_by} needs the split file {source} the cache {latents} was encoded from, "
                        "and it is missing")
    return source


def wall_slots(latents: str, start: int, stop: int) -> np.ndarray | None:
    """(N, K) bool: the slots that hold a wall, from the split file the cache was encoded
    from (its `kind` map); None, with a warning, when that file is gone."""

    source = cache_source(latents)
    if source is None or not Path(source).is_file():
        warnings.warn(f"the split file {source} the cache {latents} was encoded from is missing: "
                      "training goes on as if its videos had no walls", stacklevel=2)
        return None
    with store.open_dataset(source) as file:
        return store.wall_mask(file, start, stop)


def object_places(latents: str, start: int, stop: int) -> np.ndarray:
    """(N, T, K, 3) float32: each slot's centre x, y (up) and size (radius or half side) in world units,
    per frame, from the split file the cache was encoded from."""
    with store.open_dataset(source_split(latents, "outside_refill")) as file:
        columns = list(file["states"].attrs["state_columns"])
        states = store.read_states(file, start, stop)[..., [columns.index(c) for c in ("x", "y", "size")]]
        scale = WORLD / file["rgbd"].shape[2]
    states = states * scale
    states[..., 1] = WORLD - states[..., 1]
    return states.astype(np.float32)


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
    before, after = seen_neighbours(visible)
    frames = torch.arange(mean.shape[1], device=mean.device).view(1, -1, 1)
    nearest = torch.where(frames - before <= after - frames, before, after)    # the earlier on a tie
    stays = (walls & visible.any(dim=1)).unsqueeze(1)                           # (N, 1, K)
    return torch.where(stays.unsqueeze(-1), take_frames(mean, nearest), mean), visible | stays


def fingerprint(state: dict[str, Tensor], prefixes: tuple[str, ...] = ("transformer1.", "dynamics.")) -> str:
    """A short hash of the frozen networks' weights: which xpl.pt a proposal checkpoint belongs to."""
    digest = hashlib.sha256()
    for name in sorted(state):
        if name.startswith(prefixes):
            digest.update(name.encode())
            digest.update(state[name].detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def train_proposal(run_dir: str | os.PathLike, latents: str | os.PathLike | None = None, *, resume: bool = False,
                   overwrite: bool = False, progress: bool = True, model_overrides: dict | None = None,
                   device: str = "cpu", **train_overrides: Any) -> Path:
    """What `xvoe train proposal` does: train Transformer 2 and the existence head of
    RUN_DIR/xpl.pt further on -log q(hidden object | the rest), on objects hidden in every
    frame of the training videos (the simulator's trajectories, encoded), into
    RUN_DIR/proposal.pt. In the joint stage they get one step in each of the XPL's few steps
    and a hidden object is a rare draw; the explanation and the NLL's proposal need more.
    The network is the xpl.pt's: `model_overrides` that change it are refused.
    Also under torchrun (or `launch.on_cores`), as the XPL stage, on `device`."""
    run_dir = Path(run_dir)
    place = setup_distributed(device)
    xpl_path, xpl, xpl_state = run_xpl(run_dir, "the xpl stage", proposal=False)
    ckpt = checkpoint_path(run_dir, "proposal")
    recipe_name = recipe_of(xpl_state["config"])
    if resume and ckpt.exists():
        state = load_checkpoint(ckpt, "proposal")
        config = from_dict(TrainConfig, state["train"])
        xpl.config = from_dict(XPLConfig, state["config"]["xpl"])
    else:
        config = recipe(recipe_name).proposal_train
    xpl.config = override_resumed(xpl.config, model_overrides, what="proposal run")
    config = start_process(override(config, **train_overrides), place)
    latents = latents or recorded_input(xpl_state, xpl_path, "latents")
    batches = ProposalBatches(str(latents), batch_size=config.batch_size, shards=config.data_shards, rank=place.rank,
                              world=place.world, max_videos=config.max_videos, seed=config.seed,
                              focus_group=config.focus_group, focus_share=config.focus_share)
    meta = {"latents": str(Path(latents).resolve()), "xpl": str(xpl_path.resolve()),
            "xpl_fingerprint": fingerprint(xpl_state["model"])}
    networks = ProposalNetworks(xpl.to(place.device), batches.empty)
    job = Job("proposal", networks, batches.batch, {"recipe": recipe_name, "xpl": to_dict(xpl.config)}, meta=meta,
              item_bytes=batches.item_bytes)
    return fit(job, config, run_dir, place=place, resume=resume, overwrite=overwrite, progress=progress)


def run_xpl(run_dir: Path, needs: str, **loading: bool) -> tuple[Path, XPL, dict]:
    """RUN_DIR/xpl.pt, loaded (`load_xpl` with `loading`), for a stage that trains on top of it;
    an error naming what to train first (`needs`) if it is missing."""
    xpl_path = checkpoint_path(run_dir, "xpl")
    if not xpl_path.is_file():
        raise XvoeError(f"no xpl.pt in {run_dir}: train {needs} first")
    return (xpl_path, *load_xpl(xpl_path, **loading))


def load_xpl(model: str | os.PathLike, stage: str = "xpl", device: str | torch.device = "cpu",
             proposal: bool = True) -> tuple[XPL, dict]:
    """A trained XPL (or PLATO) model in eval mode, and its checkpoint's contents. An xpl.pt
    with a proposal.pt beside it (the proposal stage ran) gets that checkpoint's Transformer 2
    and existence head, unless `proposal` is False."""
    path = resolve_run(model, stage)
    state = load_checkpoint(path, stage, device)
    xpl = XPL(from_dict(XPLConfig, state["config"]["xpl"]))
    load_weights(xpl, state, path)
    tuned = path.parent / "proposal.pt"
    if proposal and state["stage"] == "xpl" and tuned.is_file():
        extra = load_checkpoint(tuned, "proposal", device)
        if extra["meta"].get("xpl_fingerprint") != fingerprint(state["model"]):
            raise XvoeError(f"{tuned} was trained on another xpl.pt than {path}; retrain it "
                            "(xvoe train proposal --overwrite) or move it away")
        load_weights(xpl, extra, tuned, strict=False)
        xpl.config = from_dict(XPLConfig, extra["config"]["xpl"])     # how its Transformer 2 is used, too
        state["proposal"] = str(tuned)
    elif proposal and state["stage"] == "xpl" and not xpl.config.joint_proposal:
        raise XvoeError(f"{path} leaves Transformer 2 to the proposal stage, and no proposal.pt is beside it: "
                        f"train it first (xvoe train proposal --out {path.parent})")
    state["path"] = str(path)
    return xpl.to(device).eval(), state
