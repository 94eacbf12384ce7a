"""HDF5 storage of a split: the schema every other part of xvoe reads.

One file per split. `rgbd` (N,T,H,W,4) and `ids` (N,T,H,W) are chunked one video per
chunk and deflate-compressed; the chunks are compressed by the workers that render them
and written as they are (`write_direct_chunk`), so the writer never becomes the bottleneck
and the bytes do not depend on the number of workers. Small per-video arrays are kept in
memory and written at the end. A file is written under a temporary name and renamed when
complete, so a crash never leaves a half-written file that looks valid.
"""
from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from ..errors import XvoeError
from .render import DEPTH_FAR, STATE_COLUMNS, Video
from .world import KIND_NAMES, MAX_SLOTS, WALL_KINDS

SCHEMA_VERSION = 1
GENERATOR_VERSION = "1.0"
DEFLATE_LEVEL = 2            # higher levels cost far more time for little (docs/decisions.md, "HDF5 compression level")
TEST_LABELS = ("scenario", "setting", "pair", "member", "possible", "event_frame")
TRAIN_LABELS = ("group", "has_wall", "event_frame")
SPLITS = ("train", "test")


@dataclass
class EncodedVideo:
    """A rendered video with its big arrays already compressed, ready for the writer."""

    rgbd: bytes
    ids: bytes
    states: np.ndarray
    kind: np.ndarray
    color: np.ndarray
    labels: dict = field(default_factory=dict)


def encode(video: Video, labels: dict) -> EncodedVideo:
    return EncodedVideo(zlib.compress(video.rgbd.tobytes(), DEFLATE_LEVEL),
                        zlib.compress(video.ids.tobytes(), DEFLATE_LEVEL),
                        video.states, video.kind, video.color, labels)


def _label_dtype(name: str):
    if name in ("scenario", "setting", "group"):
        return h5py.string_dtype("utf-8")
    if name in ("possible", "has_wall"):
        return np.bool_
    if name in ("pair", "event_frame"):
        return np.int32
    return np.int8


class Writer:
    """Fills the datasets of one split file, video by video, in index order."""

    def __init__(self, file: h5py.File, split: str, count: int, frames: int, size: int):
        self.file, self.split, self.count = file, split, count
        kwargs = dict(compression="gzip", compression_opts=DEFLATE_LEVEL, track_times=False)
        self.rgbd = file.create_dataset("rgbd", (count, frames, size, size, 4), np.uint8,
                                        chunks=(1, frames, size, size, 4), **kwargs)
        self.ids = file.create_dataset("ids", (count, frames, size, size), np.uint8,
                                       chunks=(1, frames, size, size), **kwargs)
        self.states = np.zeros((count, frames, MAX_SLOTS, len(STATE_COLUMNS)), np.float32)
        self.kind = np.zeros((count, MAX_SLOTS), np.int8)
        self.color = np.zeros((count, MAX_SLOTS, 3), np.uint8)
        names = TEST_LABELS if split == "test" else TRAIN_LABELS
        self.labels = {name: [None] * count for name in names}
        self.written = 0

    def add(self, video: EncodedVideo) -> None:
        i = self.written
        self.rgbd.id.write_direct_chunk((i, 0, 0, 0, 0), video.rgbd)
        self.ids.id.write_direct_chunk((i, 0, 0, 0), video.ids)
        self.states[i], self.kind[i], self.color[i] = video.states, video.kind, video.color
        for name, values in self.labels.items():
            values[i] = video.labels[name]
        self.written += 1

    def finish(self) -> None:
        if self.written != self.count:
            raise XvoeError(f"only {self.written} of {self.count} videos were written")
        small = dict(track_times=False)
        self.file.create_dataset("states", data=self.states, **small).attrs["state_columns"] = list(STATE_COLUMNS)
        self.file.create_dataset("kind", data=self.kind, **small)
        self.file.create_dataset("color", data=self.color, **small)
        for name, values in self.labels.items():
            self.file.create_dataset(name, data=np.array(values, dtype=_label_dtype(name)), **small)


@contextmanager
def atomic_file(path: str | os.PathLike, overwrite: bool = False) -> Iterator[h5py.File]:
    """An HDF5 file open for writing under a temporary name, renamed to `path` on success."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise XvoeError(f"{path} exists; pass --overwrite to replace it")
    if not path.parent.exists():
        raise XvoeError(f"directory {path.parent} does not exist")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with h5py.File(tmp, "w", track_order=False) as file:
            yield file
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_attributes(file: h5py.File, split: str, config: dict, seed: int) -> None:
    file.attrs["xvoe_schema"] = SCHEMA_VERSION
    file.attrs["generator_version"] = GENERATOR_VERSION
    file.attrs["split"] = split
    file.attrs["seed"] = seed
    file.attrs["config"] = json.dumps(config, sort_keys=True)
    file.attrs["kind_names"] = list(KIND_NAMES)
    file.attrs["depth_far"] = DEPTH_FAR


def open_hdf5(path: str | os.PathLike) -> h5py.File:
    """An HDF5 file open for reading, or a one-line error if it is missing or not HDF5."""
    path = Path(path)
    if not path.is_file():
        raise XvoeError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError:
        raise XvoeError(f"{path} is not an HDF5 file") from None


def open_dataset(path: str | os.PathLike) -> h5py.File:
    """Open an xvoe split file for reading, or say in one line why it is not one."""
    file = open_hdf5(path)
    version = file.attrs.get("xvoe_schema")
    if version is None:
        file.close()
        raise XvoeError(f"{path} is not an xvoe dataset (no xvoe_schema attribute)")
    if int(version) != SCHEMA_VERSION:
        file.close()
        raise XvoeError(f"{path} has xvoe schema version {int(version)}; this xvoe reads version {SCHEMA_VERSION}")
    return file


def config_of(file: h5py.File) -> dict:
    return json.loads(file.attrs["config"])


def wall_mask(file: h5py.File, start: int, stop: int) -> np.ndarray:
    """(N, K) bool: the slots of videos [start, stop) that hold a wall, from the kind map."""
    names = list(file.attrs["kind_names"])
    return np.isin(file["kind"][start:stop], [names.index(name) for name in WALL_KINDS if name in names])


def strings(file: h5py.File, name: str) -> np.ndarray:
    """A string label column as a numpy array of str."""
    return file[name].asstr()[:]


def copy_videos(source: h5py.File, writer: Writer) -> None:
    """Append every video of `source` to `writer`, moving the compressed chunks as they are."""
    states, kind, color = source["states"][:], source["kind"][:], source["color"][:]
    labels = {name: source[name].asstr()[:] if source[name].dtype.kind == "O" else source[name][:]
              for name in writer.labels}
    for i in range(states.shape[0]):
        _, rgbd = source["rgbd"].id.read_direct_chunk((i, 0, 0, 0, 0))
        _, ids = source["ids"].id.read_direct_chunk((i, 0, 0, 0))
        writer.add(EncodedVideo(rgbd, ids, states[i], kind[i], color[i],
                                {name: values[i] for name, values in labels.items()}))
