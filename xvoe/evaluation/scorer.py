"""A model ready to score (`Scorer`) and how it reads a test split: loaded by name, path or
reference (`load_model`), its videos encoded once per batch by its perception module
(`encode_videos`), and the MSE score's per-frame curves of an encoded batch (`mse_curves`).

The PhyDNet baseline predicts pixels, not latents: its per-frame surprise is the squared
error of its one-step prediction summed over pixels (0 at frame 0), kept in s_dyn beside an
s_img of zeros (`PhyDNetSurprise`). The random agent and a model of your own answer
`surprise(videos)` (xvoe.evaluation.user_models) with one term of their own.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
import torch
from torch import Tensor

from ..domains import TIME_LIMIT
from ..errors import XvoeError
from ..models.devices import device_of, mixed_precision, resolve_device
from ..models.nll import InferenceConfig
from ..models.perception import ComponentVAE, normalise
from ..models.phydnet import PhyDNet
from ..models.xpl import XPL
from ..scenes import store
from ..training.checkpoints import SHIPPED, shipped_path
from ..training.data import check_size, visible_threshold
from ..training.latents import LATENT_CHUNK, encode_frames
from ..training.perception import load_perception
from ..training.phydnet import load_phydnet
from ..training.provenance import recipe_differences
from ..training.recipes import recipe_of
from ..training.stages import PERCEPTION, PHYDNET, RANDOM
from ..training.stages import XPL as XPL_STAGE
from ..training.xpl import load_xpl, model_nll, nll_origin
from .surprise import BETTER, PROPOSED, DrawnScene, every_explanation
from .user_models import (
    SurpriseModel,
    Videos,
    checked_model,
    checked_surprise,
    curve_of,
    load_surprise_model,
    read_videos,
)

__all__ = ["MSE_CURVES", "MSE_LABEL", "EncodedChunk", "PhyDNetSurprise", "RandomAgent", "Scorer", "as_scorer",
           "checkpoint_settings", "custom_curves", "encode", "encode_chunk",
           "encode_video", "encode_videos", "load_model", "mse_curves", "names_code", "open_test_split",
           "own_surprise"]

# the MSE score's per-frame curves of a batch (`mse_curves`), in the order a curves file stores them:
# the default verdict's terms, the seen slots' reconstruction error, the paper's terms
MSE_CURVES = ("s_img", "s_dyn", "s_rec", "paper_s_img", "paper_s_dyn")
MSE_LABEL = "squared pixel error"       # the unit of the MSE curves, on every axis that draws them


class RandomAgent:
    """The chance baseline, as any model is written: per-frame surprise drawn uniformly, from
    a generator of each video's own (so a video scores the same in any batch or shard)."""

    name = RANDOM

    def __init__(self, seed: int = 0):
        self.seed = seed

    def surprise(self, videos: Videos) -> np.ndarray:
        return np.stack([np.random.default_rng([self.seed, int(i)]).random(videos.frames) for i in videos.index])


class PhyDNetSurprise:
    """The PhyDNet baseline as a surprise model: its one-step prediction error per frame."""

    name = PHYDNET
    curve, curve_label = "s_dyn", MSE_LABEL

    def __init__(self, net: PhyDNet):
        self.net, self.image_size = net, net.config.image_size

    def surprise(self, videos: Videos) -> Tensor:
        device = device_of(self.net)
        with mixed_precision(device):
            return self.net.surprise(normalise(torch.from_numpy(videos.rgbd).to(device))).float()


@dataclass
class Scorer:
    """A model ready to score: the perception module and one dynamics stage (XPL, PLATO), or a
    `SurpriseModel` (PhyDNet, the random agent, a model of your own). Every one answers the
    same `surprise(videos)`; the XPL family's scores also keep their terms apart (s_img,
    s_dyn, s_rec) and feed extra columns such as the NLL's."""

    name: str
    vae: ComponentVAE | None
    xpl: XPL | None
    phydnet: PhyDNet | None = None
    custom: SurpriseModel | None = None
    # the MSE score's explanation (xvoe.evaluation.surprise): "better", the better of Transformer 2's
    # proposal and nothing hidden (the default verdict), or "proposal", always Transformer 2's (the paper's)
    explanation: str = BETTER
    # the NLL surprise's settings (XPL with reasoning only): those its checkpoint stores, else its
    # recipe's, else InferenceConfig's defaults; `nll_origin` says which, and the NLL says so where
    # not the checkpoint's. None: a model made in memory, scored with the defaults
    nll: InferenceConfig | None = None
    nll_origin: str = "defaults"
    # what `load_model` was given (a shipped name, an absolute path, package.module:name), for
    # `xvoe verify` to load the model again; None for a model made in memory
    source: str | None = None
    # seconds a `custom` model's surprise may take for one batch (None: no limit)
    time_limit: float | None = TIME_LIMIT
    # where the settings of each checkpoint read came from, for the header (`checkpoint_settings`);
    # None for a model made in memory or of your own
    settings: dict | None = None

    @property
    def is_random(self) -> bool:
        return isinstance(self.custom, RandomAgent)

    def surprise(self, videos: Videos) -> np.ndarray | Tensor:
        """Per-frame surprise (B, T), the protocol every model answers: s_img + s_dyn for XPL."""
        if self.custom is not None:
            return self.custom.surprise(videos)
        curves, _ = mse_curves(self, encode(self, videos))
        prefix = "" if self.explanation == BETTER else "paper_"
        return curves[f"{prefix}s_img"] + curves[f"{prefix}s_dyn"]

    @property
    def device(self) -> torch.device:
        """Where its networks are (a model of your own places its tensors itself: the CPU here)."""
        network = self.phydnet or self.vae
        return device_of(network) if network is not None else torch.device("cpu")

    @property
    def image_size(self) -> int | None:
        if self.custom is not None:
            return getattr(self.custom, "image_size", None)
        return (self.phydnet or self.vae).config.image_size

    def without_reasoning(self) -> Scorer:
        """The same perception and dynamics with both Transformers off: a predictive-only
        observer, PLATO's kind, made from this model (for a class without a shipped PLATO)."""
        if self.xpl is None:
            raise XvoeError(f"{self.name} has no XPL model to take the reasoning out of")
        bare = XPL(replace(self.xpl.config, use_reasoning=False))
        bare.dynamics.load_state_dict(self.xpl.dynamics.state_dict())
        return Scorer(f"{self.name} without reasoning", self.vae, bare.to(self.device).eval())


def load_model(model: str, device: str | torch.device = "cpu") -> Scorer:
    """`random`, a shipped model's name (`SHIPPED`), a run directory (its xpl.pt), a stage checkpoint (xpl.pt, plato.pt,
    xpl-noresidual.pt with perception.pt beside it; phydnet.pt), RUN_DIR/STAGE, or a model of your own,
    `package.module:name` or `path/to/file.py:name` (`SurpriseModel`). `device`: where its networks
    run (cpu, cuda, cuda:N, mps; refused in one line where this machine has none such)."""
    device = resolve_device(device)
    if model == RANDOM:
        return Scorer(RANDOM, None, None, custom=RandomAgent(), source=RANDOM)
    if names_code(model):
        custom = load_surprise_model(model)
        return Scorer(custom.name, None, None, custom=custom, source=_absolute_reference(model))

    path = Path(model)
    if model in SHIPPED and not path.exists():
        shipped = shipped_path(model)
        if shipped is None:
            raise XvoeError(f"the model {model} is not shipped with this copy of xvoe; train it with xvoe pipeline")
        run_dir, stage = shipped.parent, model
    elif path.is_file():
        run_dir, stage = path.parent, path.stem
    elif path.name in SHIPPED and (path.parent / f"{path.name}.pt").is_file():
        run_dir, stage = path.parent, path.name
    else:
        run_dir, stage = path, XPL_STAGE
    if stage not in SHIPPED:
        raise XvoeError(f"{model} is not a model to score with: give a run directory, one of "
                        f"{', '.join(s + '.pt' for s in SHIPPED)}, or {RANDOM!r}")
    if stage == PHYDNET:
        net, state = load_phydnet(run_dir / "phydnet.pt", device)
        return Scorer(stage, None, None, phydnet=net, custom=PhyDNetSurprise(net), source=_absolute_reference(model),
                      settings=checkpoint_settings({stage: state}))
    vae, perception = load_perception(run_dir, device)
    xpl, state = load_xpl(run_dir, stage, device)
    config, reasoning = state["config"], xpl.config.use_reasoning
    return Scorer(stage, vae, xpl, nll=model_nll(config) if reasoning else None,
                  nll_origin=nll_origin(config) if reasoning else "defaults", source=_absolute_reference(model),
                  settings=checkpoint_settings({PERCEPTION: perception, stage: state}))


def checkpoint_settings(states: dict[str, dict]) -> dict[str, dict]:
    """Where the settings of each checkpoint of a model came from, by stage: the recipe it names,
    and the settings in which it differs from that recipe (`recipe_differences`: given on the
    command line, `--set`, when it was trained, or a run not finished), none where the recipe
    made it. What a score file's header records beside the NLL's sources (`nll_source`)."""
    found = {}
    for stage, state in states.items():
        try:
            changed = recipe_differences(state)
        except XvoeError:       # a recipe this copy of xvoe does not have
            changed = ["the recipe is not one of this xvoe's: its settings cannot be compared"]
        found[stage] = {"recipe": recipe_of(state["config"]), "changed from the recipe": changed}
    return found


def names_code(model: str) -> bool:
    """Whether `load_model(model)` imports and runs code (a model of your own, `module:name` or
    `file.py:name`) rather than reading weights, which never runs code."""
    return ":" in model and not Path(model).exists()


def _absolute_reference(model: str) -> str:
    """`model` as `load_model` takes it from any directory: a path (or a file.py of file.py:name) made
    absolute; a shipped name or package.module:name as it is."""
    where, colon, name = model.rpartition(":")
    if colon and where.endswith(".py") and Path(where).is_file():
        return f"{Path(where).resolve()}:{name}"
    return str(Path(model).resolve()) if Path(model).exists() else model


def as_scorer(model: str | Scorer | SurpriseModel, device: str | torch.device = "cpu") -> Scorer:
    """A model as `score` and `explain` take it: a name or path (`load_model`), a `Scorer`, or an
    object of your own answering `surprise(videos)` (`SurpriseModel`), scored on the CPU as given."""
    if isinstance(model, str):
        return load_model(model, device)
    if isinstance(model, Scorer):
        return model
    custom = checked_model(model, type(model).__name__)
    return Scorer(custom.name, None, None, custom=custom)


def own_surprise(scorer: Scorer) -> bool:
    """Whether a scorer's surprise is one term of its own (a model of your own, the random agent),
    whose score file holds the score column alone: PhyDNet's is its prediction error, kept in
    s_dyn beside an s_img of zeros as the MSE's terms are."""
    return scorer.custom is not None and scorer.phydnet is None


def custom_curves(scorer: Scorer, file, start: int, stop: int) -> dict[str, np.ndarray]:
    """The per-frame curves (B, T) by name of videos [start, stop) of an open test split under a
    model answering `surprise(videos)`, its term checked (`checked_surprise`): a model of your own
    or the random agent keeps it under its own name (`curve_of`); PhyDNet's prediction error is
    s_dyn, beside an s_img of zeros, as the MSE's terms are."""
    own = own_surprise(scorer)
    name = curve_of(scorer.custom)[0]
    videos = read_videos(file, start, stop)
    surprise = checked_surprise(scorer.custom, videos, scorer.time_limit)
    if own:
        return {name: surprise}
    zeros = np.zeros_like(surprise)
    return {"s_img": zeros, "s_dyn": surprise, "paper_s_img": zeros, "paper_s_dyn": surprise}


@contextmanager
def open_test_split(scorer: Scorer, data: str | os.PathLike) -> Iterator[h5py.File]:
    """A test split open for reading, refused in one line unless the scorer reads its frames' size."""
    with store.open_dataset(data, split="test") as file:
        if scorer.image_size is not None:
            check_size(file, scorer.image_size, f"the model {scorer.name}")
        yield file


def encode_videos(scorer: Scorer, file, start: int, stop: int, latents: h5py.File | None = None) -> dict[str, Tensor]:
    """Videos [start, stop) of an open test split, encoded: frames, latents, visibility, walls;
    read from `latents`, the split's open latent cache (`latent_cache`), where given."""
    videos = read_videos(file, start, stop)
    if latents is None:
        return encode(scorer, videos)
    return _on_device(scorer, videos, torch.from_numpy(latents["mean"][start:stop]),
                     torch.from_numpy(latents["visible"][start:stop]),
                     torch.from_numpy(latents["background_mean"][start:stop]))


@dataclass
class EncodedChunk:
    """The videos of one latent cache chunk, encoded as a score encodes them (`encode_chunk`): what
    an explanation of any of them reads, so that explaining each video of a chunk encodes it once."""

    first: int                      # the chunk's first video in the split
    videos: dict[str, Tensor]       # `encode_videos` of its videos

    def holds(self, index: int) -> bool:
        return 0 <= index - self.first < len(self.videos["mean"])

    def video(self, index: int) -> dict[str, Tensor]:
        """Video `index` of the split (which the chunk holds) as a batch of one."""
        row = index - self.first
        return {name: value[row:row + 1] for name, value in self.videos.items()}


def encode_chunk(scorer: Scorer, file, index: int) -> EncodedChunk:
    """The latent cache chunk (LATENT_CHUNK videos from 0) of video `index` of an open test split,
    encoded as the split's latent cache and an uncached score at the default batch encode them."""
    start = index - index % LATENT_CHUNK
    return EncodedChunk(start, encode_videos(scorer, file, start, min(start + LATENT_CHUNK, len(file["rgbd"]))))


def encode_video(scorer: Scorer, file, index: int) -> dict[str, Tensor]:
    """Video `index` of an open test split, encoded as its score encodes it (a batch of one):
    among the videos of its latent cache chunk (`encode_chunk`). Alone, the encoder's passes
    hold other images and float rounding moves its latents (and its NLL by up to 6e-4 nats)."""
    return encode_chunk(scorer, file, index).video(index)


def encode(scorer: Scorer, videos: Videos) -> dict[str, Tensor]:
    """A batch of videos encoded by the scorer's perception module: frames, latents, visibility,
    walls, on the scorer's device."""
    count, frames_count, size = videos.rgbd.shape[:3]
    encoded = encode_frames(scorer.vae, videos.rgbd.reshape(-1, size, size, 4), videos.ids.reshape(-1, size, size),
                            videos.walls.shape[1])
    shaped = {k: torch.from_numpy(v).reshape(count, frames_count, *v.shape[1:]) for k, v in encoded.items()}
    return _on_device(scorer, videos, shaped["mean"], shaped["pixels"] > visible_threshold(size),
                     shaped["background_mean"])


def _on_device(scorer: Scorer, videos: Videos, mean: Tensor, visible: Tensor, background: Tensor) -> dict[str, Tensor]:
    """A batch as the surprise reads it (frames, latents, visibility, background, walls), on the scorer's device."""
    batch = {"frames": normalise(torch.from_numpy(videos.rgbd)), "mean": mean, "visible": visible,
             "background": background, "occluder": torch.from_numpy(videos.walls)}
    return {name: value.to(scorer.device) for name, value in batch.items()}


def mse_curves(scorer: Scorer, batch: dict[str, Tensor]) -> tuple[dict[str, Tensor], DrawnScene]:
    """The `MSE_CURVES` (B, T) of encoded videos (`encode_videos`) under XPL or PLATO, both
    explanations from one set of decodes (s_rec is the same under both: it draws the seen slots),
    and the scene drawn, for the NLL to read rather than draw again."""
    videos = (batch["mean"], batch["visible"], batch["background"], batch["occluder"])
    with mixed_precision(scorer.device):
        found, scene = every_explanation(scorer.vae, scorer.xpl, batch["frames"], *videos)
    default, paper = found[BETTER], found[PROPOSED]
    curves = {"s_img": default.s_img, "s_dyn": default.s_dyn, "s_rec": default.s_rec,
              "paper_s_img": paper.s_img, "paper_s_dyn": paper.s_dyn}
    return {name: curve.float() for name, curve in curves.items()}, scene.full_precision()
