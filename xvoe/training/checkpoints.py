"""Checkpoints on disk: writing them safely, reading them with a clear error, finding them.

A checkpoint is a dict saved by torch (format, stage, step, config, model, optimiser, train,
meta). The shipped models are checkpoints too, in the package's weights directory, so that a
name such as `xpl` resolves wherever a run directory does.
"""
from __future__ import annotations

import io
import os
import pickle
from pathlib import Path

import numpy as np
import torch

from ..errors import XvoeError
from ..models.config import from_dict
from ..models.devices import on_cpu
from ..outputs import atomic_paths
from .config import TrainConfig
from .recipes.recipe import NETWORKS
from .stages import PERCEPTION, SCORED, STAGES

__all__ = ["CHECKPOINT_FORMAT", "WEIGHTS", "SHIPPED", "save_checkpoint", "load_checkpoint", "recorded_input",
           "first_not_finite", "load_weights", "resolve_run", "shipped_path"]

CHECKPOINT_FORMAT = 1
WEIGHTS = Path(__file__).resolve().parent.parent / "weights"
SHIPPED = SCORED         # every model a checkpoint holds ships under its stage's name
# Run checkpoints written before the RNG state was saved as tensors hold numpy's generator key as
# an array; these (numpy's own array rebuilder first) make arrays from bytes and call nothing else.
_NUMPY_ARRAYS = [np.ndarray(0).__reduce__()[0], np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def save_checkpoint(path: Path, state: dict, beside: dict[Path, bytes] | None = None) -> None:
    """Write `path` and the files `beside` it (a stage's loss CSV) under temporary names and
    rename them together (xvoe.outputs.atomic_paths): an interrupted save leaves the last
    checkpoint and its files, never a broken one or a mismatched pair. Serialised in memory
    first, so that a full disk fails a plain write, named in one line, not torch's archive
    writer. Its tensors are saved from the CPU, so that a checkpoint names no device and loads
    on any."""
    buffer = io.BytesIO()
    torch.save(on_cpu(state), buffer)
    files = {**(beside or {}), Path(path): buffer.getvalue()}
    with atomic_paths(*files) as temporaries:
        for temporary, data in zip(temporaries, files.values()):
            temporary.write_bytes(data)


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
    # the stages xvoe trains are checked; the loop's other callers (a test's toy stage) read their own
    if state.get("stage") in STAGES and (problem := _contents_problem(state)) is not None:
        raise XvoeError(f"{path} does not fit the {state.get('stage')} model: {problem}")
    if (bad := first_not_finite(state)) is not None:
        raise XvoeError(f"{path} holds weights that are not finite ({bad}); the run that wrote it diverged")
    return state


def recorded_input(state: dict, path: str | os.PathLike, key: str, flag: str = "--data") -> str:
    """The input a resumed run trained on, as its checkpoint records it (`meta[key]`), or a
    one-line error asking for it where none is recorded (a shipped model keeps no paths)."""
    if not state.get("meta", {}).get(key):
        raise XvoeError(f"{path} records no {key} to resume on (a shipped model?); give it with {flag}")
    return state["meta"][key]


_WEIGHT_KEYS = ("model", "trained")      # "trained" beside "model" when a run averages its weights


def _contents_problem(state: dict) -> str | None:
    """What in a checkpoint of a known format is not what its stage stores, naming the key, or
    None: its model config of the stage's fields and types, the training config's, a whole
    step, and weights that are tensors by name. Read here, where every loader passes, so that
    no loader meets a bad value deep in a network."""
    entry = STAGES[state["stage"]]
    if not isinstance(state.get("config"), dict):
        return f"config is a {type(state.get('config')).__name__}, not a dict"
    if entry.config_key not in state["config"]:
        return f"config has no {entry.config_key}"
    stored = [(f"config.{entry.config_key}", NETWORKS[entry.config_key], state["config"][entry.config_key])]
    stored += [("train", TrainConfig, state["train"])] if "train" in state else []
    for key, cls, value in stored:
        try:
            from_dict(cls, value, key)
        except XvoeError as error:
            return str(error)
    step = state.get("step", 0)
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        return f"step is {step!r}, not a whole number of steps"
    if not isinstance(state.get("meta", {}), dict):
        return f"meta is a {type(state['meta']).__name__}, not a dict"
    if "model" not in state:
        return "it has no model key (the weights)"
    for key in (key for key in _WEIGHT_KEYS if key in state):
        if not isinstance(state[key], dict):
            return f"{key} is a {type(state[key]).__name__}, not a dict of tensors"
        for name, value in state[key].items():
            if not isinstance(name, str) or not isinstance(value, torch.Tensor):
                return f"{key} entry {name!r} is a {type(value).__name__}, not a tensor"
    return None


def first_not_finite(state: dict) -> str | None:
    """The first weight of a checkpoint (`_WEIGHT_KEYS`) holding a NaN or an infinity, as
    "KEY NAME", or None."""
    for key in (key for key in _WEIGHT_KEYS if key in state):
        for name, tensor in state[key].items():
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                return f"{key} {name}"
    return None


def load_weights(module: torch.nn.Module, state: dict, path: str | os.PathLike, key: str = "model",
                 strict: bool = True) -> None:
    """Load a checkpoint's weights `state[key]` into `module`, or say in one line which tensor
    does not fit (missing, unknown to the network, or of another shape); with `strict` false
    (a checkpoint of part of the network) only those it holds must fit."""
    expected, found = module.state_dict(), state[key]
    problem = None
    for name, tensor in found.items():
        if name not in expected:
            problem = f"{key} holds {name}, which the model has not"
        elif tensor.shape != expected[name].shape:
            problem = f"{name} has shape {tuple(tensor.shape)}, the model {tuple(expected[name].shape)}"
        if problem:
            break
    missing = [name for name in expected if name not in found] if strict else []
    if problem is None and missing:
        problem = f"{key} lacks {missing[0]}" + (f" and {len(missing) - 1} more" if len(missing) > 1 else "")
    if problem is not None:
        raise XvoeError(f"{path} does not fit the {state.get('stage')} model: {problem}")
    module.load_state_dict(found, strict=strict)


def resolve_run(model: str | os.PathLike, stage: str = PERCEPTION) -> Path:
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
    PERCEPTION for the perception module XPL-family models share), or None."""
    if name not in SHIPPED:
        return None
    path = WEIGHTS / f"{stage or name}.pt"
    return path if path.is_file() else None
