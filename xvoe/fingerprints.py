"""What a result was made from, as hashes that hold across machines and paths: the split a
score file was scored on and the model that scored it.

A score file records both (xvoe.evaluation.score_headers, `score_header`), so that `xvoe metrics`
can refuse scores of another split and `xvoe verify` can load the same model again. Hashes
are of contents, never of file names, times or compressed bytes.
"""
from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from .scenes.store import read_frames

__all__ = ["arrays_hash", "file_hash", "split_identity", "describe_split"]

_HASH_CHARS = 16         # 64 bits of sha256: no accidental collision, short enough to read in a report
_SAMPLED_VIDEOS = 64     # videos whose frames the split's content hash reads (evenly spaced, first and last kept)


def _digest(update: Iterable[bytes]) -> str:
    found = hashlib.sha256()
    for chunk in update:
        found.update(chunk)
    return found.hexdigest()[:_HASH_CHARS]


def _array_bytes(name: str, array: np.ndarray) -> Iterable[bytes]:
    """A named array as bytes that fix its name, type, shape and values (strings as UTF-8)."""
    array = np.asarray(array)
    if array.dtype.kind in "OUS":
        array = np.array([str(v) for v in array.ravel()], dtype=object).reshape(array.shape)
        yield json.dumps([name, "str", list(array.shape)]).encode()
        yield "\0".join(array.ravel().tolist()).encode()
        return
    array = np.ascontiguousarray(array)
    yield json.dumps([name, array.dtype.str, list(array.shape)]).encode()
    yield array.tobytes()


def arrays_hash(arrays: Mapping[str, np.ndarray], settings: Mapping | None = None) -> str:
    """The hash of named arrays, in name order, and of settings as canonical JSON: a model's
    weights and configs hash alike wherever the checkpoint lies and whatever else it holds
    (optimiser state, step, paths)."""
    def chunks() -> Iterable[bytes]:
        for name in sorted(arrays):
            yield from _array_bytes(name, arrays[name])
        yield json.dumps(settings or {}, sort_keys=True, default=str).encode()
    return _digest(chunks())


def file_hash(path: str | Path) -> str:
    """The hash of a file's bytes (a user model's source file)."""
    return _digest([Path(path).read_bytes()])


def _sampled_videos(count: int) -> np.ndarray:
    """The rows whose frames `split_identity` reads: at most SAMPLED_VIDEOS, evenly spaced, the
    first and the last among them."""
    return np.unique(np.linspace(0, count - 1, min(count, _SAMPLED_VIDEOS)).round().astype(int)) if count else \
        np.zeros(0, int)


def split_identity(file) -> dict:
    """The identity of an open split file (h5py.File): its seed, a hash of its generator config,
    its video count and a content hash.

    The content hash covers every label, `kind`, `color` and `states` whole (any change of scene
    changes the states) and the frames (`rgbd`, `ids`) of the `_sampled_videos` only, with the
    frames' shape: a pixel changed in a video outside the sample is not seen. It reads 64
    videos and the small arrays: a 1,000-pair split at 32x32 in 2 s, 5 s from a cold disk
    (docs/decisions.md, "Score files that say what they are")."""
    count = file["rgbd"].shape[0]
    labels = [name for name in ("scenario", "setting", "pair", "member", "possible", "event_frame", "group",
                                "has_wall") if name in file]
    rows = _sampled_videos(count)

    def chunks() -> Iterable[bytes]:
        yield json.dumps(["rgbd", list(file["rgbd"].shape)]).encode()
        for name in (*labels, "kind", "color", "states"):
            values = file[name].asstr()[:] if file[name].dtype.kind == "O" else file[name][:]
            yield from _array_bytes(name, values)
        for row in rows:
            yield from _array_bytes(f"rgbd {row}", read_frames(file, "rgbd", row))
            yield from _array_bytes(f"ids {row}", read_frames(file, "ids", row))
    config = json.dumps(json.loads(file.attrs["config"]), sort_keys=True)
    return {"seed": int(file.attrs["seed"]), "config_hash": _digest([config.encode()]), "videos": int(count),
            "content_hash": _digest(chunks())}


def describe_split(identity: Mapping) -> str:
    """A split's identity in a few words, for an error or a report."""
    return (f"seed {identity.get('seed')}, {identity.get('videos')} videos, config {identity.get('config_hash')}, "
            f"content {identity.get('content_hash')}")
