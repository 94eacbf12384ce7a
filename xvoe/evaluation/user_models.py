"""A model of your own, as `xvoe score --model package.module:name` (or `path/to/file.py:name`)
takes it: what it is given (`Videos`), the protocol it answers (`SurpriseModel`), how it is
loaded, and the checks its answers pass before anything is written.

Being the user's code, it runs under a time limit per batch, and whatever it raises or returns
wrong ends the run in one line naming it (`checked_surprise`); its per-frame curve is stored
under the model's own name for it (`curve_of`), and it passes the harness of
xvoe.evaluation.checks (`check_model`).
"""
from __future__ import annotations

import importlib
import importlib.util
import re
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from torch import Tensor

from ..errors import XvoeError
from ..scenes import store
from .checks import check_batches, check_finite, sample_rows
from .score_tables import model_name_problem

__all__ = ["SurpriseModel", "Videos", "check_model", "checked_model", "checked_surprise", "curve_of",
           "load_surprise_model", "one_line", "read_videos", "run_model", "stack_videos"]


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


def read_videos(file, start: int, stop: int) -> Videos:
    """Videos [start, stop) of an open test split as a surprise model sees them."""
    rgbd = store.read_frames(file, "rgbd", start, stop)
    return Videos(rgbd, store.read_frames(file, "ids", start, stop), rgbd.shape[1], store.wall_mask(file, start, stop),
                  np.arange(start, stop))


def stack_videos(videos: list[Videos]) -> Videos:
    """Batches of videos as one batch, in the order given."""
    return Videos(np.concatenate([v.rgbd for v in videos]), np.concatenate([v.ids for v in videos]),
                  videos[0].frames, np.concatenate([v.walls for v in videos]),
                  np.concatenate([v.index for v in videos]))


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


def checked_surprise(model: SurpriseModel, videos: Videos, time_limit: float | None) -> np.ndarray:
    """`model.surprise(videos)` as floats (B, T), within `time_limit` seconds, refused in one line
    naming the model (and the first video at fault) unless it returns, returns real numbers of
    that shape, and every one is finite; an exception of the model's is named too."""
    values = _real_values(run_model(model, "surprise", videos, time_limit), videos, model.name)
    check_finite(values, videos.index, model.name)
    return values


def run_model(model: SurpriseModel, method: str, videos: Videos, time_limit: float | None) -> object:
    """`model.METHOD(videos)` (`surprise`, `explain`) within `time_limit` seconds (None: no limit);
    what it raises (an exception, or sys.exit) or a batch past the limit ends in one line naming
    the model and the videos."""
    batch = _batch_name(videos.index)
    try:
        with _time_limit(time_limit):
            return getattr(model, method)(videos)
    except _OutOfTime:
        raise XvoeError(f"the model {model.name} gave no {method} for {batch} within {time_limit:g} s; "
                        "--time-limit sets the limit per batch") from None
    except XvoeError:
        raise
    except (Exception, SystemExit) as error:  # noqa: BLE001 - a user's model may fail in any way; say which and where
        raise XvoeError(f"the model {model.name} failed on {batch}: {method} raised {one_line(error)}") from None


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


def check_model(model: SurpriseModel, time_limit: float | None, file, first: int, last: int) -> None:
    """The harness's batch checks (xvoe.evaluation.checks) on a seeded sample of videos [first, last)."""
    rows = sample_rows(first, last)
    sample = [read_videos(file, row, row + 1) for row in rows]
    check_batches(lambda positions: checked_surprise(model, stack_videos([sample[p] for p in positions]), time_limit),
                  rows, model.name)
