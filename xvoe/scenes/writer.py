"""Writing a split: one HDF5 file, video by video, in the schema `store` reads.

`rgbd` (N,T,H,W,4) and `ids` (N,T,H,W) are chunked one video per chunk and deflate-compressed;
the chunks are compressed by the workers that render them and written as they are
(`write_direct_chunk`), so the writer never becomes the bottleneck and the bytes do not depend
on the number of workers. Small per-video arrays are kept in memory and written at the end. A
file is written under a temporary name and renamed when complete, so a crash never leaves a
half-written file that looks valid.
"""
from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import h5py
import numpy as np

from ..errors import XvoeError
from ..outputs import atomic_paths, claim_file, claim_scope
from .render import DEPTH_FAR, STATE_COLUMNS, Video
from .store import GENERATOR_VERSION, SCHEMA_VERSION, TEST_LABELS, TRAIN_LABELS, damaged
from .world import KIND_NAMES, MAX_SLOTS

__all__ = ["DEFLATE_LEVEL", "EncodedVideo", "Writer", "atomic_file", "copy_videos", "encode", "held_per_video",
           "write_attributes"]

DEFLATE_LEVEL = 2            # higher levels cost far more time for little (docs/decisions.md, "Speed and memory")


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


def held_per_video(frames: int) -> int:
    """Bytes a `Writer` holds in memory per video until it finishes (the states, kinds, colours
    and labels; the frames go to disk as they come), for a size to be checked before the work."""
    return frames * MAX_SLOTS * len(STATE_COLUMNS) * 4 + MAX_SLOTS * 4 + 8 * 64


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

    def add(self, video: EncodedVideo, at: int | None = None) -> None:
        """Store the next video, or with `at` the video of that row (an import whose source
        order is not the schema's)."""
        i = self.written if at is None else at
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
    """An HDF5 file open for writing under a temporary name, renamed to `path` on success;
    `path` is held from the claim to the rename (xvoe.outputs). With no chunk cache: each chunk
    is written whole as it comes, so a full disk fails that write; a cached chunk whose write
    fails as the dataset closes leaves HDF5 to crash the process at the file's close."""
    with claim_scope():
        path = claim_file(path, overwrite)
        with atomic_paths(path) as (tmp,), h5py.File(tmp, "w", track_order=False, rdcc_nbytes=0) as file:
            yield file


def write_attributes(file: h5py.File, split: str, config: dict, seed: int) -> None:
    file.attrs["xvoe_schema"] = SCHEMA_VERSION
    file.attrs["generator_version"] = GENERATOR_VERSION
    file.attrs["split"] = split
    file.attrs["seed"] = seed
    file.attrs["config"] = json.dumps(config, sort_keys=True)
    file.attrs["kind_names"] = list(KIND_NAMES)
    file.attrs["depth_far"] = DEPTH_FAR


def _checked_chunk(source: h5py.File, name: str, video: int) -> bytes:
    """The compressed chunk of `video`'s `name` as stored, decompressed once to check it: a
    damaged chunk copied unread would only fail whoever reads the merged split."""
    dataset = source[name]
    try:
        mask, chunk = dataset.id.read_direct_chunk((video,) + (0,) * (dataset.ndim - 1))
        whole = len(zlib.decompress(chunk)) == np.prod(dataset.chunks) * dataset.dtype.itemsize
    except (OSError, zlib.error):
        whole = False
    if not whole or mask:       # a filter skipped (mask) is not how xvoe writes a chunk either
        raise XvoeError(damaged(source.filename, name, video))
    return chunk


def copy_videos(source: h5py.File, writer: Writer) -> None:
    """Append every video of `source` to `writer`, moving the compressed chunks as they are
    (each checked on the way, `_checked_chunk`)."""
    states, kind, color = source["states"][:], source["kind"][:], source["color"][:]
    labels = {name: source[name].asstr()[:] if source[name].dtype.kind == "O" else source[name][:]
              for name in writer.labels}
    for i in range(states.shape[0]):
        rgbd = _checked_chunk(source, "rgbd", i)
        ids = _checked_chunk(source, "ids", i)
        writer.add(EncodedVideo(rgbd, ids, states[i], kind[i], color[i],
                                {name: values[i] for name, values in labels.items()}))
