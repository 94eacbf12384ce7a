"""Checkpoints on disk: writing them safely, reading them with a clear error, finding them.

A checkpoint is a dict saved by torch (format, stage, step, config, model, optimiser, train,
meta). The shipped models are checkpoints too, in the package's weights directory, so that a
name such as `xpl` resolves wherever a run directory does.
"""
from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import torch

from ..errors import XvoeError
from ..models.devices import on_cpu
from .stages import SCORED

CHECKPOINT_FORMAT = 1
WEIGHTS = Path(__file__).resolve().parent.parent / "weights"
SHIPPED = SCORED         # every model a checkpoint holds ships under its stage's name
# Run checkpoints written before the RNG state was saved as tensors hold numpy's generator key as
# an array; these (numpy's own array rebuilder first) make arrays from bytes and call nothing else.
_NUMPY_ARRAYS = [np.ndarray(0).__reduce__()[0], np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def save_checkpoint(path: Path, state: dict) -> None:
    """Write to a temporary name and rename: an interrupted save never leaves a broken checkpoint.
    Its tensors are saved from the CPU, so that a checkpoint names no device and loads on any."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        torch.save(on_cpu(state), tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def load_checkpoint(path: str | os.PathLike, stage: str | None = None, device: str | torch.device = "cpu") -> dict:
    """A checkpoint written by this loop (of `stage`, if given), its tensors on `device`, or a
    one-line error. Only tensors and plain data are read: a pickled object is refused, never built.
    A checkpoint of one kind under another's name would be used as the kind it holds and
    labelled as the one named."""
    path = Path(path)
    if not path.is_file():
        raise XvoeError(f"{path}: no such checkpoint")
    try:
        # weights_only: tensors and plain data only, so a checkpoint from elsewhere never runs code
        with torch.serialization.safe_globals(_NUMPY_ARRAYS):
            state = torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as error:
        if "Unsupported global" not in str(error):       # not a pickle of ours at all
            raise XvoeError(f"{path} is not a readable xvoe checkpoint (UnpicklingError)") from None
        raise XvoeError(f"{path} holds objects other than tensors and plain data; xvoe does not load it "
                        "(loading such a file can run code)") from None
    except Exception as error:  # noqa: BLE001 - any unreadable file gets the same one-line message
        raise XvoeError(f"{path} is not a readable xvoe checkpoint ({type(error).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise XvoeError(f"{path} is not an xvoe checkpoint of format {CHECKPOINT_FORMAT}")
    if stage is not None and state.get("stage") != stage:
        raise XvoeError(f"{path} holds a {state.get('stage')} model, not {stage}: load it under its own name "
                        f"({state.get('stage')}.pt)")
    return state


def resolve_run(model: str | os.PathLike, stage: str = "perception") -> Path:
    """A checkpoint from a file, a run directory holding STAGE.pt, a run name under runs/, or
    the name of a shipped model (`SHIPPED`)."""
    path = Path(model)
    candidates = [path, path / f"{stage}.pt", Path("runs") / path / f"{stage}.pt"]
    if str(model) in SHIPPED:
        candidates.append(WEIGHTS / f"{stage}.pt")
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise XvoeError(f"no {stage} checkpoint at {model} (tried {', '.join(map(str, candidates))})")


def shipped_path(name: str, stage: str | None = None) -> Path | None:
    """The shipped checkpoint of model `name` for `stage` (the model's own by default;
    "perception" for the perception module XPL-family models share), or None."""
    if name not in SHIPPED:
        return None
    path = WEIGHTS / f"{stage or name}.pt"
    return path if path.is_file() else None
