"""Scoring a test split with a trained model: one CSV row per video and the per-frame curves.

Decoding is the cost, so videos are encoded once per batch and every column (the MSE terms,
and any a higher layer adds, such as the NLL's) is computed from that one encoding. A split is
encoded once for every model that reads the same perception module: the first score writes its
latent cache beside the split (xvoe.training.latents, `split_cache`) and the others read it.

The PhyDNet baseline predicts pixels, not latents: its per-frame surprise is the squared
error of its one-step prediction summed over pixels (0 at frame 0). It is written in the
s_dyn column and curve; s_img is all zeros for it.

A model answering `surprise(videos)` (`SurpriseModel`: PhyDNet, the random agent, a model of
your own) has one term: its score file holds the score column alone (PhyDNet's keeps it in
s_dyn too, beside an s_img of zeros, `own_surprise`); its per-frame curve is stored under the
model's own name for it (`curve_of`), and it passes the harness of xvoe.evaluation.checks
before anything is written. Being the user's code, it runs under a time limit per batch, and
whatever it raises or returns wrong ends the run in one line naming it (`checked_surprise`).
"""
from __future__ import annotations

import csv
import importlib
import importlib.metadata
import importlib.util
import json
import os
import re
import signal
import sys
import threading
import warnings
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import h5py
import numpy as np
import torch
from torch import Tensor

from ..domains import TIME_LIMIT
from ..errors import XvoeError
from ..fingerprints import arrays_hash, describe_split, file_hash, split_identity
from ..models.config import to_dict
from ..models.devices import device_of, mixed_precision, resolve_device
from ..models.nll import InferenceConfig
from ..models.perception import ComponentVAE, normalise
from ..models.phydnet import PhyDNet
from ..models.xpl import XPL
from ..outputs import atomic_paths, claim_file, claim_scope
from ..progress import progress_bar
from ..scenes import store
from ..training.checkpoints import SHIPPED, shipped_path
from ..training.data import check_size, visible_threshold
from ..training.latents import (
    LATENT_CHUNK,
    check_cache,
    encode_frames,
    encode_with,
    encoder_key,
    open_latents,
    split_cache,
)
from ..training.perception import load_perception
from ..training.phydnet import load_phydnet
from ..training.xpl import load_xpl, nll_settings_of
from .checks import check_batches, check_finite, check_spread, sample_rows
from .metrics import excess
from .score_tables import model_name_problem, scores_digest
from .surprise import DrawnScene, aggregate, draw_scene, every_explanation

# score, s_img and s_dyn: the default verdict (for XPL, the better of two explanations); paper_score:
# the paper's (XPL: always Transformer 2's proposal), the same for a model with no such choice
SCORE_COLUMNS = ("index", "model", "scenario", "setting", "pair", "member", "possible", "score", "s_img", "s_dyn",
                 "paper_score")
# the per-frame curves beside a score file, in this order (then any extra columns' own: the NLL's
# nll); the paper's score is the sum of the last two
CURVES = ("s_img", "s_dyn", "s_rec", "paper_s_img", "paper_s_dyn")
MSE_LABEL = "squared pixel error"       # the unit of the MSE curves, on every axis that draws them
EXCESS_COLUMNS = ("s_rec", "excess")    # models with a perception module: XPL, its ablation, PLATO


@dataclass
class Videos:
    """A batch of test videos as a surprise model sees them: no labels, nothing from the future
    of the file."""

    rgbd: np.ndarray        # (B, T, H, W, 4) uint8: RGB, and depth (near is dark)
    ids: np.ndarray         # (B, T, H, W) uint8: the slot each pixel shows (0: background)
    frames: int             # T
    walls: np.ndarray       # (B, K) bool: the slots that are walls (occluders), as the masks show them
    index: np.ndarray       # (B,) the videos' rows in the split: a seed per video, not a label


class SurpriseModel(Protocol):
    """Your own model, as `xvoe score --model package.module:name` (or `path/to/file.py:name`)
    takes it: an object, or a factory of one, with a `name` and a `surprise` method; an
    `image_size` attribute, if it has one, is checked against the split's frames. It may also
    have `explain(videos)`, the frames (B, T, H, W, C >= 3) uint8 of what it believes is behind
    the wall, which `xvoe explain` draws under the video, and `curve` and `curve_label`, the
    name its per-frame surprise is stored under and the axis it is drawn on (`curve_of`).
    docs/evaluate-your-model.md walks through one."""

    name: str

    def surprise(self, videos: Videos) -> np.ndarray | Tensor:
        """Per-frame surprise (B, T), higher for more surprising; a video's score is its sum."""


class RandomAgent:
    """The chance baseline, as any model is written: per-frame surprise drawn uniformly, from
    a generator of each video's own (so a video scores the same in any batch or shard)."""

    name = "random"

    def __init__(self, seed: int = 0):
        self.seed = seed

    def surprise(self, videos: Videos) -> np.ndarray:
        return np.stack([np.random.default_rng([self.seed, int(i)]).random(videos.frames) for i in videos.index])


class PhyDNetSurprise:
    """The PhyDNet baseline as a surprise model: its one-step prediction error per frame."""

    name = "phydnet"
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
    explanation: str = "better"
    # the NLL surprise's settings its checkpoint stores (its recipe's; XPL with reasoning only). None:
    # it stores none, and the NLL takes InferenceConfig's defaults and says so
    nll: InferenceConfig | None = None
    # what `load_model` was given (a shipped name, an absolute path, package.module:name), for
    # `xvoe verify` to load the model again; None for a model made in memory
    source: str | None = None
    # seconds a `custom` model's surprise may take for one batch (None: no limit)
    time_limit: float | None = TIME_LIMIT

    @property
    def is_random(self) -> bool:
        return isinstance(self.custom, RandomAgent)

    def surprise(self, videos: Videos) -> np.ndarray | Tensor:
        """Per-frame surprise (B, T), the protocol every model answers: s_img + s_dyn for XPL."""
        if self.custom is not None:
            return self.custom.surprise(videos)
        curves, _ = _xpl_curves(self, encode(self, videos))
        prefix = "" if self.explanation == "better" else "paper_"
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
    if model == "random":
        return Scorer("random", None, None, custom=RandomAgent(), source="random")
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
        run_dir, stage = path, "xpl"
    if stage not in SHIPPED:
        raise XvoeError(f"{model} is not a model to score with: give a run directory, one of "
                        f"{', '.join(s + '.pt' for s in SHIPPED)}, or 'random'")
    if stage == "phydnet":
        net = load_phydnet(run_dir / "phydnet.pt", device)[0]
        return Scorer(stage, None, None, phydnet=net, custom=PhyDNetSurprise(net), source=_absolute_reference(model))
    vae, _ = load_perception(run_dir, device)
    xpl, state = load_xpl(run_dir, stage, device)
    return Scorer(stage, vae, xpl, nll=nll_settings_of(state["config"]) if xpl.config.use_reasoning else None,
                  source=_absolute_reference(model))


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


def model_identity(scorer: Scorer) -> dict:
    """What a score file records of its model: a hash of its weights and configs (stable across
    machines, paths and what else the checkpoint holds: the run's xpl.pt and the shipped xpl hash
    alike), or for a model of your own its `module:name` and the hash of its source file."""
    found = {"source": scorer.source}
    if scorer.is_random:
        return found | {"seed": scorer.custom.seed}
    if scorer.custom is not None and scorer.phydnet is None:
        return found | _module_identity(scorer)
    modules = {"perception": scorer.vae, "dynamics": scorer.xpl, "phydnet": scorer.phydnet}
    arrays = {f"{part}.{name}": tensor.detach().cpu().numpy() for part, module in modules.items() if module is not None
              for name, tensor in module.state_dict().items()}
    configs = {part: to_dict(module.config) for part, module in modules.items() if module is not None}
    return found | {"checkpoint_hash": arrays_hash(arrays, configs)}


def _module_identity(scorer: Scorer) -> dict:
    """A model of your own as `module:name` and the hash of the file that defines it."""
    if scorer.source is None:       # made in memory: its class names it
        kind = type(scorer.custom)
        where, name = kind.__module__, kind.__qualname__
        origin = getattr(sys.modules.get(where), "__file__", None)
    else:
        where, _, name = scorer.source.rpartition(":")
        origin = where if where.endswith(".py") else getattr(importlib.util.find_spec(where), "origin", None)
        where = Path(where).stem if where.endswith(".py") else where
    return {"module": f"{where}:{name}", "file_hash": file_hash(origin) if origin and Path(origin).is_file() else None}


def own_surprise(scorer: Scorer) -> bool:
    """Whether a scorer's surprise is one term of its own (a model of your own, the random agent),
    whose score file holds the score column alone: PhyDNet's is its prediction error, kept in
    s_dyn beside an s_img of zeros as the MSE's terms are."""
    return scorer.custom is not None and scorer.phydnet is None


def surprise_definitions(scorer: Scorer, how: str) -> dict:
    """The surprise definitions behind a score file's columns, with their settings (the NLL's are
    added beside them by its `ExtraColumns`)."""
    if scorer.custom is not None:
        kept = " (in s_dyn)" if scorer.phydnet is not None else ""
        return {"own": f"the model's per-frame surprise{kept}, {how} over frames"}
    return {"mse": {"score": "better", "paper_score": "proposal", "aggregate": how}}


def load_surprise_model(reference: str) -> SurpriseModel:
    """The object `name` of `package.module:name` or `path/to/file.py:name`; a class or another
    factory is called with no arguments. A one-line error for anything that is not a model, and
    for a module or factory that fails in any way (an exception, or sys.exit)."""
    where, _, name = reference.rpartition(":")
    try:
        if where.endswith(".py"):
            if not Path(where).is_file():
                raise XvoeError(f"{where}: no such file")
            spec = importlib.util.spec_from_file_location(Path(where).stem, where)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
        else:
            module = importlib.import_module(where)
    except XvoeError:
        raise
    except (Exception, SystemExit) as error:  # noqa: BLE001 - a user's module may fail in any way; say which and where
        raise XvoeError(f"cannot import {where} for the model {reference}: {one_line(error)}") from None
    found = getattr(module, name, None)
    if found is None:
        raise XvoeError(f"{where} has no {name!r} for the model {reference}")
    if isinstance(found, type) or (callable(found) and not hasattr(found, "surprise")):
        try:
            found = found()
        except (Exception, SystemExit) as error:  # noqa: BLE001 - a user's constructor may fail in any way
            raise XvoeError(f"the model {reference} could not be made: {name}() raised {one_line(error)}") from None
    return checked_model(found, reference)


def checked_model(model: object, reference: str) -> SurpriseModel:
    """`model` if it answers the protocol (`SurpriseModel`): a `surprise` method, a name that is
    one line of printable text, a valid `curve`; else a one-line error naming `reference`."""
    name = getattr(model, "name", None)
    if not callable(getattr(model, "surprise", None)) or not isinstance(name, str):
        raise XvoeError(f"{reference} is not a surprise model: it needs a name (str) and a surprise(videos) "
                        "method (docs/evaluate-your-model.md)")
    problem = model_name_problem(name)
    if problem is not None:
        raise XvoeError(f"the model {reference}'s name {problem}")
    curve_of(model)
    return model


def as_scorer(model: str | Scorer | SurpriseModel, device: str | torch.device = "cpu") -> Scorer:
    """A model as `score` and `explain` take it: a name or path (`load_model`), a `Scorer`, or an
    object of your own answering `surprise(videos)` (`SurpriseModel`), scored on the CPU as given."""
    if isinstance(model, str):
        return load_model(model, device)
    if isinstance(model, Scorer):
        return model
    custom = checked_model(model, type(model).__name__)
    return Scorer(custom.name, None, None, custom=custom)


def one_line(error: BaseException) -> str:
    """An exception of a user's code as one line: its type and its message, whitespace collapsed."""
    message = " ".join(str(error).split())
    return f"{type(error).__name__}: {message[:300]}" if message else type(error).__name__


def curve_of(model: SurpriseModel) -> tuple[str, str]:
    """The name a model's per-frame surprise is stored under in the curves file and the axis
    label it is drawn with: its `curve` and `curve_label`, by default "surprise" for both (a
    model's own surprise is in its own units, not the MSE's squared pixel error)."""
    curve = getattr(model, "curve", "surprise")
    label = getattr(model, "curve_label", curve)
    if not isinstance(curve, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,39}", curve) or curve == "header":
        raise XvoeError(f"the model {model.name}'s curve must be a name of letters, digits, _ and - (up to 40, "
                        f"not 'header'), not {curve!r}")
    if not isinstance(label, str) or not label.strip() or "\n" in label:
        raise XvoeError(f"the model {model.name}'s curve_label must be one line of text, not {label!r}")
    return curve, label


def custom_surprise(scorer: Scorer, file, start: int, stop: int) -> np.ndarray:
    """A model of your own's per-frame surprise (B, T) of videos [start, stop), checked."""
    return checked_surprise(scorer, read_videos(file, start, stop))


def checked_surprise(scorer: Scorer, videos: Videos) -> np.ndarray:
    """`scorer.custom.surprise(videos)` as floats (B, T), within the scorer's time limit, refused in
    one line naming the model (and the first video at fault) unless it returns, returns real
    numbers of that shape, and every one is finite; an exception of the model's is named too."""
    values = _real_values(run_model(scorer, "surprise", videos), videos, scorer.name)
    check_finite(values, videos.index, scorer.name)
    return values


def run_model(scorer: Scorer, method: str, videos: Videos) -> object:
    """`scorer.custom.METHOD(videos)` (`surprise`, `explain`) within the scorer's time limit; what
    it raises (an exception, or sys.exit) or a batch past the limit ends in one line naming the
    model and the videos."""
    batch = _batch_name(videos.index)
    try:
        with _time_limit(scorer.time_limit):
            return getattr(scorer.custom, method)(videos)
    except _OutOfTime:
        raise XvoeError(f"the model {scorer.name} gave no {method} for {batch} within {scorer.time_limit:g} s; "
                        "--time-limit sets the limit per batch") from None
    except XvoeError:
        raise
    except (Exception, SystemExit) as error:  # noqa: BLE001 - a user's model may fail in any way; say which and where
        raise XvoeError(f"the model {scorer.name} failed on {batch}: {method} raised {one_line(error)}") from None


def _batch_name(index: np.ndarray) -> str:
    """Videos of a batch as a message names them: one, a run of them, or the first few."""
    if len(index) == 1:
        return f"video {index[0]}"
    if np.array_equal(index, np.arange(index[0], index[0] + len(index))):
        return f"videos {index[0]}..{index[-1]}"
    return f"videos {', '.join(map(str, index[:3]))}, ... ({len(index)} videos)"


def _real_values(found: object, videos: Videos, name: str) -> np.ndarray:
    """A model's surprise (B, T) as float64, or a one-line error naming the first video whose row
    is not T real numbers (text, complex numbers, a ragged row), or the shape found."""
    expected = videos.rgbd.shape[:2]
    if isinstance(found, Tensor):
        found = found.detach().cpu()
        found = found if found.is_complex() else found.double()
    try:
        values = np.asarray(found)
    except (ValueError, TypeError):
        values = None
    numbers = values is not None and values.dtype.kind in "biuf"
    if numbers and values.shape == expected:
        return values.astype(float)
    rows = found if not numbers and (isinstance(found, (list, tuple)) or getattr(found, "ndim", 0) > 0) else ()
    for row, video in zip(rows, videos.index):
        problem = _row_problem(row, expected[1])
        if problem:
            raise XvoeError(f"the model {name} gave {problem} for video {video}; surprise(videos) returns "
                            f"real numbers of shape (videos, frames), {expected}")
    shape = values.shape if values is not None else type(found).__name__
    raise XvoeError(f"the model {name} gave surprise of shape {shape} for {expected[0]} videos of {expected[1]} "
                    f"frames; expected {expected}")


def _row_problem(row: object, frames: int) -> str | None:
    """What makes one video's row of a model's surprise not `frames` real numbers, or None."""
    try:
        values = np.asarray(row)
    except (ValueError, TypeError):
        return "a ragged row"
    if values.dtype.kind == "c":
        return "complex numbers"
    if values.dtype.kind not in "biuf":
        return f"values of type {values.dtype} (not numbers)"
    if values.shape != (frames,):
        return f"a row of shape {values.shape}, not ({frames},)"
    return None


class _OutOfTime(BaseException):
    """Raised into a model's surprise when its time is up: not an Exception, so that a model that
    catches every Exception cannot swallow it."""


@contextmanager
def _time_limit(seconds: float | None) -> Iterator[None]:
    """`_OutOfTime` raised after `seconds` of wall time (a timer signal: the main thread only;
    elsewhere, or with None, no limit)."""
    if seconds is None or threading.current_thread() is not threading.main_thread():
        yield
        return

    def expire(number: int, frame) -> None:
        raise _OutOfTime

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def check_model(scorer: Scorer, file, first: int, last: int) -> None:
    """The harness's batch checks (xvoe.evaluation.checks) on a seeded sample of videos [first, last)."""
    rows = sample_rows(first, last)
    sample = [read_videos(file, row, row + 1) for row in rows]
    check_batches(lambda positions: checked_surprise(scorer, stack_videos([sample[p] for p in positions])), rows,
                  scorer.name)


def stack_videos(videos: list[Videos]) -> Videos:
    """Batches of videos as one batch, in the order given."""
    return Videos(np.concatenate([v.rgbd for v in videos]), np.concatenate([v.ids for v in videos]),
                  videos[0].frames, np.concatenate([v.walls for v in videos]),
                  np.concatenate([v.index for v in videos]))


class ExtraColumns(Protocol):
    """Columns that a higher layer adds to a score file (the NLL's: inference.score.NLLColumns):
    checked against the scorer, computed batch by batch from the encoded videos, finished once
    every video is in; with per-frame curves of its own, written beside the `CURVES`."""

    names: tuple[str, ...]
    curve_names: tuple[str, ...]

    def check(self, scorer: Scorer) -> None:
        """A one-line XvoeError if the scorer cannot give these columns."""

    def batch(self, scorer: Scorer, videos: dict[str, Tensor], scene: DrawnScene) -> tuple[np.ndarray, np.ndarray]:
        """Per-video values (B, C) of a batch of `encode_videos`, and its curves (len(curve_names), B, T);
        `scene`: what the MSE score drew of the batch (xvoe.evaluation.surprise.draw_scene)."""

    def finish(self, values: np.ndarray, curves: np.ndarray, size: int) -> np.ndarray:
        """The columns (N, len(names)) from every batch's values (N, C), the `CURVES` (5, N, T)
        and the frame size."""

    def settings(self) -> dict:
        """What the columns were made with, for the score file's header (`score_header`)."""


@claim_scope()
def score_split(model: str | Scorer, data: str, out: str, *, how: str = "sum", videos_per_batch: int = 16,
                extra: ExtraColumns | None = None, score_column: str = "score", shard: tuple[int, int] = (0, 1),
                checks: bool = True, overwrite: bool = False, progress: bool = True,
                device: str | torch.device = "cpu", cache: str | os.PathLike | bool = True,
                time_limit: float | None = TIME_LIMIT) -> Path:
    """One CSV row per test video, and the per-frame surprise curves (s_img, s_dyn: (N, T);
    s_rec too for a model with a perception module) in an .npz beside it, with the header
    (`score_header`). Models with a perception module also get the columns s_rec and excess
    (xvoe.evaluation.surprise). `extra` adds columns after these (and its curves beside the
    others); `score_column` names one of them to be the score instead of the MSE score. `shard`
    (I, N) scores part I of N, whole batches of it, so that `merge_scores` of the parts writes
    the bytes one run would have. `checks`: a model answering `surprise(videos)` passes the
    harness of xvoe.evaluation.checks (on the shard's videos) before anything is written; False
    skips all but the finite check. `device`: where a model given by name runs (a `Scorer` runs
    where it was loaded). `cache`: the latent cache of the split that a model with a perception
    module reads instead of encoding its frames (`latent_cache`): True, the split's beside it;
    a path; False, none (every batch encoded here). `time_limit`: seconds a model answering
    `surprise(videos)` may take for one batch before the run ends in one line (None: none)."""
    if how not in ("sum", "max"):
        raise XvoeError(f"--aggregate must be sum or max, not {how!r}")
    if score_column != "score" and (extra is None or score_column not in extra.names):
        raise XvoeError(f"the score column must be 'score' or one of the extra columns, not {score_column!r}")
    if time_limit is not None and not time_limit > 0:
        raise XvoeError(f"--time-limit must be a number of seconds above 0, not {time_limit}")
    scorer = replace(as_scorer(model, device), time_limit=time_limit)
    if extra is not None:
        extra.check(scorer)
    with open_test_split(scorer, data) as file:
        # after every check of the input: a refused run leaves nothing behind
        out = claim_file(out, overwrite)
        curves_path = claim_file(out.with_suffix(".curves.npz"), overwrite, what="the curves beside --out")
        first, last = shard_rows(file["rgbd"].shape[0], videos_per_batch, shard)
        identity = split_identity(file)     # the header's, and the cache's key
        # the parts of a sharded run may run at once: each reads a cache, none makes one
        latents = latent_cache(scorer, data, cache, make=shard == (0, 1), progress=progress, identity=identity)
        checks = checks and scorer.custom is not None
        if checks:
            check_model(scorer, file, first, last)
        labels = store.labels(file, ("scenario", "setting", "pair", "member", "possible"))
        header = {"xvoe": package_version(), "model": scorer.name, "model_identity": model_identity(scorer),
                  "split": identity, "data": str(Path(data).resolve()), "score": score_column,
                  "aggregate": how, "surprise": surprise_definitions(scorer, how),
                  **(extra.settings() if extra is not None else {})}
        with open_latents(latents) if latents is not None else nullcontext() as encoded:
            curves, added, extra_curves = score_rows(scorer, file, first, last, videos_per_batch, extra, progress,
                                                     encoded)
    columns = row_columns(scorer, curves, added, how, extra, score_column)
    if checks:
        check_spread(columns["score"], scorer.name)
    named = {name: curve for name, curve in zip(CURVES, curves) if scorer.vae is not None or name != "s_rec"}
    named |= extra_curves
    if scorer.custom is not None:       # one term, under the model's own name
        own, header["curve_label"] = curve_of(scorer.custom)
        named, header["curve"] = {own: curves[1]}, own
    # the CSV and its curves are one result: the CSV, which names the curves, is renamed last
    with atomic_paths(curves_path, out) as (curves_tmp, tmp):
        with open(tmp, "w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(SCORE_COLUMNS[:7] + tuple(columns))
            for row, i in enumerate(range(first, last)):
                writer.writerow([i, scorer.name, labels["scenario"][i], labels["setting"][i], int(labels["pair"][i]),
                                 int(labels["member"][i]), bool(labels["possible"][i])]
                                + [float(values[row]) for values in columns.values()])
        header["scores_digest"] = scores_digest(tmp)
        with open(curves_tmp, "wb") as curves_file:
            np.savez_compressed(curves_file, header=np.array(json.dumps(header, sort_keys=True)), **named)
    return out


def score_rows(scorer: Scorer, file, first: int, last: int, videos_per_batch: int, extra: ExtraColumns | None,
               progress: bool = False,
               latents: h5py.File | None = None) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """The `CURVES` (5, N, T) of videos [first, last) of an open test split, batch by batch, the
    `extra` columns (N, C), finished (C = 0 without), and the extra curves (N, T) by name.
    `latents`: the split's open latent cache, read instead of encoding (`encode_videos`)."""
    curves = np.zeros((len(CURVES), last - first, file["rgbd"].shape[1]))
    values, extra_curves = [], []
    with progress_bar(total=last - first, desc=f"score {scorer.name}", unit="video", disable=not progress) as bar:
        for start in range(first, last, videos_per_batch):
            stop = min(last, start + videos_per_batch)
            rows = slice(start - first, stop - first)
            if scorer.custom is not None:     # one term, in the s_dyn columns
                curves[[1, 4], rows] = custom_surprise(scorer, file, start, stop)
            else:
                batch = encode_videos(scorer, file, start, stop, latents)     # once, for every column
                found_curves, scene = _xpl_curves(scorer, batch)
                curves[:, rows] = torch.stack(list(found_curves.values())).cpu().numpy()
                if extra is not None:
                    found, found_curves = extra.batch(scorer, batch, scene)
                    values.append(found)
                    extra_curves.append(found_curves)
            bar.update(stop - start)
    if extra is None:
        return curves, np.zeros((last - first, 0)), {}
    named = dict(zip(extra.curve_names, np.concatenate(extra_curves, axis=1)))
    return curves, extra.finish(np.concatenate(values), curves, file["rgbd"].shape[2]), named


def row_columns(scorer: Scorer, curves: np.ndarray, added: np.ndarray, how: str, extra: ExtraColumns | None,
                score_column: str = "score") -> dict[str, np.ndarray]:
    """The numeric columns of a score file after its labels (score, s_img, s_dyn, paper_score,
    then s_rec and excess for a model with a perception module, then `extra`'s; a model of your
    own's score alone, `own_surprise`), per video, from the curves and the extra columns of
    `score_rows`."""
    total = aggregate(torch.from_numpy(curves[:2].sum(0)), how).numpy()
    if own_surprise(scorer):
        return {"score": total}
    s_img, s_dyn, s_rec = (aggregate(torch.from_numpy(c), how).numpy() for c in curves[:3])
    paper = aggregate(torch.from_numpy(curves[3:].sum(0)), how).numpy()
    columns = {"score": total, "s_img": s_img, "s_dyn": s_dyn, "paper_score": paper}
    if scorer.vae is not None:
        columns |= {"s_rec": s_rec, "excess": aggregate(torch.from_numpy(excess(*curves[:3])), how).numpy()}
    if extra is not None:
        columns |= dict(zip(extra.names, added.T))
        columns["score"] = columns[score_column]
    return columns


def stored_columns(saved: dict[str, np.ndarray], header: dict) -> dict[str, np.ndarray]:
    """The columns of a score file that its stored curves (`curves_arrays`) reduce to, by the
    aggregation its header records: score, s_img, s_dyn, s_rec, paper_score and excess, each
    where its curves are stored, and nll, -log p(video), the sum of its curve whatever the
    aggregation (the sequential Monte Carlo's; importance sampling stores none). The NLL's other
    columns are not sums of curves: `xvoe verify` rescores them."""
    how, own = header.get("aggregate", "sum"), header.get("curve")

    def reduced(curve: np.ndarray) -> np.ndarray:
        return aggregate(torch.from_numpy(np.asarray(curve, float)), how).numpy()

    found = {name: reduced(saved[name]) for name in ("s_img", "s_dyn", "s_rec") if name in saved}
    if {"paper_s_img", "paper_s_dyn"} <= set(saved):
        found["paper_score"] = reduced(saved["paper_s_img"] + saved["paper_s_dyn"])
    if {"s_img", "s_dyn", "s_rec"} <= set(saved):
        found["excess"] = reduced(excess(saved["s_img"], saved["s_dyn"], saved["s_rec"]))
    if "nll" in saved:
        found["nll"] = np.asarray(saved["nll"], float).sum(axis=1)
    score = header.get("score", "score")
    if score == "score" and own in saved:
        found["score"] = reduced(saved[own])
    elif score == "score" and {"s_img", "s_dyn"} <= set(saved):
        found["score"] = reduced(saved["s_img"] + saved["s_dyn"])
    elif score in found:
        found["score"] = found[score]
    return found


def score_header(path: str | Path, check: bool = True) -> dict:
    """What a score file was made with, kept in its curves file: the package version (`xvoe`),
    the model's name and identity (`model_identity`), the split's identity (`split`,
    `xvoe.fingerprints.split_identity`) and the path it was read from (`data`), the score column,
    the aggregation over frames, the surprise definitions (`surprise`), for the NLL its
    settings and seed (`nll`, `nll_seed`), and the digest of the scores it was written with
    (`scores_digest`). `check`: refuse, in one line, curves written with other scores
    (`check_curves_of`)."""
    curves = Path(path).with_suffix(".curves.npz")
    if not curves.is_file():
        raise XvoeError(f"{path} has no curves file beside it ({curves.name}), which holds its header")
    header = _header_of(curves, curves_arrays(curves))
    if check:
        check_curves_of(path, curves, header)
    return header


def _header_of(curves: Path, saved: dict[str, np.ndarray]) -> dict:
    try:
        header = json.loads(str(saved["header"])) if "header" in saved else {}
    except ValueError:
        header = None
    if not isinstance(header, dict):
        raise XvoeError(f"{curves} is not a curves file of xvoe score (its header is not a JSON object)")
    return header


def check_curves_of(scores: str | Path, curves: str | Path, header: dict) -> None:
    """Refuse curves whose header records the digest of other scores than the file `scores`: the
    curves of another score file put beside it, or scores edited since they were written (a
    header that records none, an older xvoe's, is taken as it is)."""
    recorded = header.get("scores_digest")
    if recorded is not None and recorded != scores_digest(scores):
        raise XvoeError(f"{curves} was written with other scores than {scores} holds: the curves of another score "
                        f"file, or scores edited since (xvoe verify {scores} names the rows)")


class UncheckedScores(UserWarning):
    """A score file that records no split (made by hand, elsewhere, or by an older xvoe): it is
    read, but whether it belongs to the split cannot be checked (docs/decisions.md, "Score files
    that say what they are")."""


def scored_split(path: str | Path) -> dict | None:
    """The identity of the split a score file was scored on (`xvoe.fingerprints.split_identity`), or
    None for a file that records none (`warn_unchecked` says so, once the file has been read)."""
    header = score_header(path, check=False) if Path(path).with_suffix(".curves.npz").is_file() else {}
    return header.get("split")


def warn_unchecked(path: str | Path) -> None:
    """A warning for a score file that records no split, after it was read without a problem."""
    if scored_split(path) is None:
        warnings.warn(f"{path} does not record the split it was scored on, so it is not checked against one; "
                      "rescore it with this xvoe to have it checked", UncheckedScores, stacklevel=2)


def check_same_split(path: str | Path, identity: dict, data: str | Path) -> None:
    """Refuse scores made on another split than `data`, whose identity is `identity`."""
    found = scored_split(path)
    if found is not None and found != identity:
        raise XvoeError(f"{path} was scored on another split ({describe_split(found)}) than {data} "
                        f"({describe_split(identity)}); score {data} instead")


def check_scored_by(path: str | Path, scorer: Scorer) -> None:
    """Refuse a score file that another model made (its weights and configs, wherever they lie)."""
    recorded = score_header(path, check=False).get("model_identity")
    if recorded is None:
        raise XvoeError(f"{path} does not record the model it was made with: rescore it with this xvoe")
    loaded = model_identity(scorer)
    if _without_source(recorded) != _without_source(loaded):
        raise XvoeError(f"{path} was scored by another model than {scorer.name}: it names {_without_source(recorded)}, "
                        f"the model is {_without_source(loaded)}")


def _without_source(identity: dict) -> dict:
    return {key: value for key, value in identity.items() if key != "source"}


@dataclass
class Curves:
    """A score file's per-frame curves as figures draw them: the MSE's terms (s_img, s_dyn, and
    s_rec for a model with a perception module), or a model's own curve alone."""

    arrays: dict[str, np.ndarray]   # name -> (N, T), one row per row of the score file
    own: str | None                 # the name of a model's own curve (`curve_of`); None: the MSE's terms
    label: str                      # what the axis measures

    @property
    def total(self) -> np.ndarray:
        """(N, T): the per-frame surprise whose sum over frames is the score."""
        return self.arrays[self.own] if self.own else self.arrays["s_img"] + self.arrays["s_dyn"]


def curves_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of a curves file, read as numbers and text only (never unpickled), or a one-line error."""
    try:
        with np.load(path, allow_pickle=False) as saved:
            return {name: saved[name] for name in saved.files}
    except (OSError, ValueError, zipfile.BadZipFile) as error:
        raise XvoeError(f"{path} is not a curves file of xvoe score ({error})") from None


def read_curves(path: str | Path, videos: int, scores: str | Path | None = None) -> Curves:
    """The curves file `path` (.curves.npz) of a score file of `videos` rows (`scores`, where
    known, whose digest it must record: `check_curves_of`); a one-line error for a missing
    file, one that is not a curves file or one of another score file."""
    path = Path(path)
    if not path.is_file():
        raise XvoeError(f"{path}: no such file; xvoe score writes the curves beside the CSV")
    saved = curves_arrays(path)
    header = _header_of(path, saved)
    if scores is not None:
        check_curves_of(scores, path, header)
    own = header.get("curve")
    needed = {own} if own else {"s_img", "s_dyn"}
    if not needed <= set(saved):
        raise XvoeError(f"{path} is not a curves file (it holds {', '.join(saved)})")
    arrays = {name: values for name, values in saved.items() if name != "header"}
    if any(len(values) != videos for values in arrays.values()):
        raise XvoeError(f"{path} does not hold the curves of its score file ({videos} videos): "
                        "they were not written together")
    return Curves(arrays, own, header.get("curve_label", MSE_LABEL) if own else MSE_LABEL)


def package_version() -> str:
    try:
        return importlib.metadata.version("xvoe")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def shard_rows(count: int, videos_per_batch: int, shard: tuple[int, int]) -> tuple[int, int]:
    """Rows [first, last) of part I of N: whole batches, so each video is scored in the batch a
    single run would score it in."""
    index, parts = shard
    if not 0 <= index < parts:
        raise XvoeError(f"--shard must be I/N with 0 <= I < N, not {index}/{parts}")
    batches = -(-count // videos_per_batch)
    if parts > batches:
        raise XvoeError(f"cannot cut {batches} batches of {videos_per_batch} videos into {parts} shards")
    first, last = index * batches // parts, (index + 1) * batches // parts
    return first * videos_per_batch, min(count, last * videos_per_batch)


@claim_scope()
def merge_scores(parts: list[str | Path], out: str | Path, overwrite: bool = False) -> Path:
    """Join the score files of `xvoe score --shard` (and their curves) into the files one run
    would have written, byte for byte; an error unless they are the parts of one split."""
    if not parts:
        raise XvoeError("--merge needs at least one part")
    out = claim_file(out, overwrite)
    curves_path = claim_file(out.with_suffix(".curves.npz"), overwrite, what="the curves beside --out")
    found = []
    for part in map(Path, parts):
        if not part.is_file() or not part.with_suffix(".curves.npz").is_file():
            raise XvoeError(f"{part} is not a scores file with its curves beside it")
        with open(part, newline="") as handle:      # the CSV's own line ends, kept
            lines = handle.read().splitlines(keepends=True)
        if len(lines) < 2:
            raise XvoeError(f"{part} holds no scores")
        found.append((int(lines[1].split(",", 1)[0]), part, lines))
    found.sort(key=lambda item: item[0])
    header, expected, rows, arrays = found[0][2][0], 0, [], {}
    for first, part, lines in found:
        if lines[0] != header:
            raise XvoeError(f"{part} has other columns than {found[0][1]}: the parts of one run have the same")
        if first != expected:
            raise XvoeError(f"the parts do not follow each other: {part} starts at video {first}, not {expected}")
        expected += len(lines) - 1
        rows += lines[1:]
        curves = part.with_suffix(".curves.npz")
        saved = curves_arrays(curves)
        check_curves_of(part, curves, _header_of(curves, saved))
        for name, values in saved.items():
            arrays.setdefault(name, []).append(_without_digest(values) if name == "header" else values)
        if len({str(header) for header in arrays.get("header", [])}) > 1:
            raise XvoeError(f"{part} was scored with other settings than {found[0][1]} (their headers differ)")
    with atomic_paths(curves_path, out) as (curves_tmp, tmp):
        with open(tmp, "w", newline="") as handle:
            handle.writelines([header, *rows])
        digest = {"scores_digest": scores_digest(tmp)}     # the whole file's, where each part recorded its own
        merged = {name: np.array(json.dumps(json.loads(a[0]) | digest, sort_keys=True)) if name == "header"
                  else np.concatenate(a) for name, a in arrays.items()}
        with open(curves_tmp, "wb") as curves_file:
            np.savez_compressed(curves_file, **merged)
    return out


def _without_digest(header: np.ndarray) -> str:
    """A part's header without its own scores' digest: what the parts of one run share."""
    found = json.loads(str(header))
    found.pop("scores_digest", None)
    return json.dumps(found, sort_keys=True)


def read_videos(file, start: int, stop: int) -> Videos:
    """Videos [start, stop) of an open test split as a surprise model sees them."""
    rgbd = store.read_frames(file, "rgbd", start, stop)
    return Videos(rgbd, store.read_frames(file, "ids", start, stop), rgbd.shape[1], store.wall_mask(file, start, stop),
                  np.arange(start, stop))


@contextmanager
def open_test_split(scorer: Scorer, data: str | os.PathLike) -> Iterator[h5py.File]:
    """A test split open for reading, refused in one line unless the scorer reads its frames' size."""
    with store.open_dataset(data, split="test") as file:
        if scorer.image_size is not None:
            check_size(file, scorer.image_size, f"the model {scorer.name}")
        yield file


@claim_scope()
def latent_cache(scorer: Scorer, data: str | os.PathLike, cache: str | os.PathLike | bool = True, *,
                 make: bool = True, progress: bool = False, identity: dict | None = None) -> Path | None:
    """The latent cache a scorer reads for the test split `data` (checked before): `cache`, or
    with True the split's own for the scorer's perception module (`split_cache`); None for a
    model without one, with `cache` False, or where it is missing and not to be made. One given
    is checked against the split and the perception (a one-line error for a stale or foreign
    one); the split's own, made from an earlier file of the split's name (a split generated again,
    a notebook's with other pairs), is derived data and made again. One to be made is claimed
    first (a folder that refuses it is named before the work; a run making it now is waited
    for, and its cache read), then written by the scorer's perception module. `identity`: the
    split's `split_identity`, where the caller has it."""
    if cache is False or scorer.vae is None:
        return None
    perception = encoder_key(scorer.vae)
    path = split_cache(data, perception) if cache is True else Path(cache)
    if _usable_cache(path, data, perception, identity, cache is True):
        return path
    if not make:
        return None
    # another run scoring this split with this perception makes the same cache: wait for it, then read it
    claim_file(path, overwrite=True, what="the latent cache", wait=True)
    if _usable_cache(path, data, perception, identity, cache is True):
        return path
    return encode_with(scorer.vae, data, path, overwrite=True, progress=progress, identity=identity)


def _usable_cache(path: Path, data: str | os.PathLike, perception: str, identity: dict | None, own: bool) -> bool:
    """Whether the cache at `path` is there and of this split and perception; one given (not
    the split's `own`) that is not is refused in one line."""
    if not path.exists():
        return False
    try:
        check_cache(path, data, perception, identity)
    except XvoeError:
        if not own:
            raise
        return False
    return True


def prepare_latents(scorer: Scorer, data: str | os.PathLike, cache: str | os.PathLike | bool = True, *,
                    progress: bool = False) -> Path | None:
    """The test split's latent cache for a scorer (`latent_cache`), made now if missing: what the
    processes of a run in parts read, made once before them."""
    with open_test_split(scorer, data):
        return latent_cache(scorer, data, cache, progress=progress)


def encode_videos(scorer: Scorer, file, start: int, stop: int, latents: h5py.File | None = None) -> dict[str, Tensor]:
    """Videos [start, stop) of an open test split, encoded: frames, latents, visibility, walls;
    read from `latents`, the split's open latent cache (`latent_cache`), where given."""
    videos = read_videos(file, start, stop)
    if latents is None:
        return encode(scorer, videos)
    return on_device(scorer, videos, torch.from_numpy(latents["mean"][start:stop]),
                     torch.from_numpy(latents["visible"][start:stop]),
                     torch.from_numpy(latents["background_mean"][start:stop]))


def encode_video(scorer: Scorer, file, index: int) -> dict[str, Tensor]:
    """Video `index` of an open test split, encoded as its score encodes it (a batch of one):
    among the videos of its latent cache chunk (LATENT_CHUNK from 0), as the split's latent
    cache and an uncached score at the default batch encode them. Alone, the encoder's passes
    hold other images and float rounding moves its latents (and its NLL by up to 6e-4 nats)."""
    start = index - index % LATENT_CHUNK
    batch = encode_videos(scorer, file, start, min(start + LATENT_CHUNK, len(file["rgbd"])))
    return {name: value[index - start:index - start + 1] for name, value in batch.items()}


def encode(scorer: Scorer, videos: Videos) -> dict[str, Tensor]:
    """A batch of videos encoded by the scorer's perception module: frames, latents, visibility,
    walls, on the scorer's device."""
    count, frames_count, size = videos.rgbd.shape[:3]
    encoded = encode_frames(scorer.vae, videos.rgbd.reshape(-1, size, size, 4), videos.ids.reshape(-1, size, size),
                            videos.walls.shape[1])
    shaped = {k: torch.from_numpy(v).reshape(count, frames_count, *v.shape[1:]) for k, v in encoded.items()}
    return on_device(scorer, videos, shaped["mean"], shaped["pixels"] > visible_threshold(size),
                     shaped["background_mean"])


def on_device(scorer: Scorer, videos: Videos, mean: Tensor, visible: Tensor, background: Tensor) -> dict[str, Tensor]:
    """A batch as the surprise reads it (frames, latents, visibility, background, walls), on the scorer's device."""
    batch = {"frames": normalise(torch.from_numpy(videos.rgbd)), "mean": mean, "visible": visible,
             "background": background, "occluder": torch.from_numpy(videos.walls)}
    return {name: value.to(scorer.device) for name, value in batch.items()}


def _xpl_curves(scorer: Scorer, batch: dict[str, Tensor]) -> tuple[dict[str, Tensor], DrawnScene]:
    """The `CURVES` (B, T) of encoded videos (`encode_videos`) under XPL or PLATO, both
    explanations from one set of decodes (s_rec is the same under both: it draws the seen slots),
    and the scene drawn, for the NLL to read rather than draw again."""
    videos = (batch["mean"], batch["visible"], batch["background"], batch["occluder"])
    with mixed_precision(scorer.device):
        scene = draw_scene(scorer.vae, scorer.xpl, *videos)
        found = every_explanation(scorer.vae, scorer.xpl, batch["frames"], *videos, scene)
    default, paper = found["better"], found["proposal"]
    curves = {"s_img": default.s_img, "s_dyn": default.s_dyn, "s_rec": default.s_rec,
              "paper_s_img": paper.s_img, "paper_s_dyn": paper.s_dyn}
    return {name: curve.float() for name, curve in curves.items()}, scene.full_precision()
