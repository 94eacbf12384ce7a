"""HDF5 storage of a split: the schema every other part of xvoe reads, opened and checked.

One file per split (written by `writer`): `rgbd` (N,T,H,W,4) and `ids` (N,T,H,W) one video per
compressed chunk, the small per-video arrays (`states`, `kind`, `color`) and one label column
per video. Opening a split checks its shapes, types and labels in one cheap pass
(`open_dataset`); every video's pixels and states are checked where they are read
(`read_frames`, `read_states`).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np

from ..errors import XvoeError
from ..resources import memory_problem
from .scenarios import SCENARIOS, TRAINING_GROUPS
from .world import WALL_KINDS

__all__ = ["GENERATOR_VERSION", "SCHEMA_VERSION", "SPLITS", "TEST_LABELS", "TRAIN_LABELS", "config_of", "damaged",
           "labels", "open_dataset", "open_hdf5", "pair_labels_problem", "read_frames", "read_states", "strings",
           "wall_mask"]

SCHEMA_VERSION = 1
GENERATOR_VERSION = "1.0"
TEST_LABELS = ("scenario", "setting", "pair", "member", "possible", "event_frame")
TRAIN_LABELS = ("group", "has_wall", "event_frame")
SPLITS = ("train", "test")


def open_hdf5(path: str | os.PathLike) -> h5py.File:
    """An HDF5 file open for reading, or a one-line error if it is missing or not HDF5."""
    path = Path(path)
    if os.path.isdir(path):     # os.path's answers, not pathlib's: a name too long to exist is no file either
        raise XvoeError(f"{path} is a directory, not a file")
    if not os.path.isfile(path):
        raise XvoeError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError:
        raise XvoeError(f"{path} is not an HDF5 file") from None


def open_dataset(path: str | os.PathLike, split: str | None = None) -> h5py.File:
    """Open an xvoe split file for reading, or say in one line why it is not one (`_schema_problem`);
    with `split`, it must be that split."""
    file = open_hdf5(path)
    version = file.attrs.get("xvoe_schema")
    if version is None:
        problem = "is not an xvoe dataset (no xvoe_schema attribute)"
    elif int(version) != SCHEMA_VERSION:
        problem = f"has xvoe schema version {int(version)}; this xvoe reads version {SCHEMA_VERSION}"
    else:
        problem = _schema_problem(file) or _value_problem(file)
    if problem is None and split is not None and file.attrs["split"] != split:
        problem = (f"is a {file.attrs['split']} split; this needs a {split} split"
                   + (" (training on impossible events is refused)" if split == "train" else ""))
    if problem is not None:
        file.close()
        raise XvoeError(f"{path} {problem}")
    return file


# the datasets of every split: (dims, numpy kind) per dataset; the uint8 ones exactly so, since
# their type is what bounds their values (_value_problem reads none of those pixels)
_ARRAYS = {"rgbd": (5, "u"), "ids": (4, "u"), "states": (4, "f"), "kind": (2, "i"), "color": (3, "u")}
_UINT8 = ("rgbd", "ids", "color")
_LABEL_KINDS = {"scenario": "O", "setting": "O", "group": "O", "possible": "b", "has_wall": "b",
               "pair": "i", "member": "i", "event_frame": "i"}


def _schema_problem(file: h5py.File) -> str | None:
    """What makes an open HDF5 file not a valid split, in a few words, or None: the split
    attribute, every dataset there with the right rank and type, the frames RGBD, one row per
    video in every dataset and label. Shapes and types only: no video is read."""
    split = file.attrs.get("split")
    if split not in SPLITS:
        return f"has no valid split attribute (found {split!r}; expected train or test)"
    for name in ("kind_names", "config"):
        if name not in file.attrs:
            return f"has no {name} attribute"
    try:
        config = config_of(file)
    except (TypeError, ValueError):
        config = None
    if not isinstance(config, dict):
        return "has a config attribute that is not a JSON object"
    labels = TEST_LABELS if split == "test" else TRAIN_LABELS
    for name, (dims, kind) in _ARRAYS.items():
        if name not in file or not isinstance(file[name], h5py.Dataset):
            return f"has no {name} dataset"
        if name in _UINT8 and file[name].dtype != np.uint8:
            return f"has a {name} dataset of type {file[name].dtype}; xvoe stores {name} as uint8 (0..255)"
        if file[name].ndim != dims or file[name].dtype.kind != kind:
            return f"has a {name} dataset of shape {file[name].shape} and type {file[name].dtype}, not {dims}-D {kind}"
    count, frames, height, width, channels = file["rgbd"].shape
    if channels != 4 or height != width:
        return f"holds {height}x{width} frames of {channels} channels; xvoe frames are square RGBD (4)"
    if height == 0 or frames == 0:
        return f"holds videos of {frames} frames of {height}x{width} pixels; a video has frames with pixels"
    slots = file["kind"].shape[1]
    expected = {"ids": (count, frames, height, width), "states": (count, frames, slots), "kind": (count, slots),
                "color": (count, slots, 3)}
    for name, shape in expected.items():
        if file[name].shape[:len(shape)] != shape:
            return (f"has a {name} dataset of shape {file[name].shape}, which does not match rgbd "
                    f"{file['rgbd'].shape} and kind {file['kind'].shape}")
    for name in labels:
        if name not in file or not isinstance(file[name], h5py.Dataset):
            return f"has no {name} label (a {split} split has {', '.join(labels)})"
        found = "O" if h5py.check_string_dtype(file[name].dtype) else file[name].dtype.kind
        if file[name].shape != (count,) or found != _LABEL_KINDS[name]:
            return (f"has a {name} label of shape {file[name].shape} and type {file[name].dtype}; "
                    f"expected one per video ({count}) of kind {_LABEL_KINDS[name]}")
    return _labels_memory_problem(file, labels)


def _labels_memory_problem(file: h5py.File, labels: tuple[str, ...]) -> str | None:
    """Whether the states and labels, which commands read whole, fit in this machine's memory:
    a split declaring more videos than it could hold is refused on opening, not at the read."""
    arrays = sum(file[name].size * file[name].dtype.itemsize for name in ("states", "kind", "color"))
    texts = sum(_TEXT_BYTES * file[name].size for name in labels if h5py.check_string_dtype(file[name].dtype))
    needed = arrays + texts + sum(file[name].size * file[name].dtype.itemsize for name in labels)
    problem = memory_problem(needed)
    return problem and f"declares {file['rgbd'].shape[0]:,} videos, whose states and labels {problem}"


_TEXT_BYTES = 64        # a label's text, read as a Python string


def _value_problem(file: h5py.File) -> str | None:
    """What makes the values of a split of the right schema wrong, in a few words, or None.

    Fast on a split of 10,000 videos (under 0.1 s on one core), since every command opens its split
    and each data-loading worker opens it again: the labels and the kind map are read whole (a
    few bytes a video), the pixels are bounded by their type (uint8, `_schema_problem`) and only
    the slot ids of the first and last video are read, a cheap pass that finds ids written by
    another program without decompressing the whole split. Every other video's ids and states
    are checked where they are read (`read_frames`, `read_states`), at a few milliseconds a
    thousand pairs.
    """
    kinds, names = file["kind"][:], len(file.attrs["kind_names"])
    if kinds.size and (kinds.min() < 0 or kinds.max() >= names):
        return f"has kind values {kinds.min()}..{kinds.max()}; they index kind_names (0..{names - 1})"
    slots, count = kinds.shape[1], kinds.shape[0]
    for i in sorted({0, count - 1}) if count else ():
        if (top := read_frames(file, "ids", i).max()) > slots:
            return f"has slot ids up to {top} in video {i}; they run 0..{slots} (0 = background)"
    columns = list(file["states"].attrs.get("state_columns", []))
    if len(columns) != file["states"].shape[3] or not {"x", "y", "present", "visible"} <= set(columns):
        return f"has states columns {columns}; expected one name per column, x, y, present and visible among them"
    if file.attrs["split"] == "train":
        return _training_labels_problem(labels(file, TRAIN_LABELS), file["rgbd"].shape[1])
    return pair_labels_problem(labels(file, TEST_LABELS), file["rgbd"].shape[1], bool(config_of(file).get("custom")))


def _event_problem(event_frame: np.ndarray, frames: int) -> str | None:
    outside = np.flatnonzero((event_frame < -1) | (event_frame >= frames))
    if outside.size:
        return (f"labels video {outside[0]} with event_frame {event_frame[outside[0]]}, outside its frames "
                f"(0..{frames - 1}, or -1 for none)")
    return None


def _training_labels_problem(found: dict[str, np.ndarray], frames: int) -> str | None:
    """What is wrong with a training split's labels, or None: known groups (`released` for
    the paper's imported videos), event frames within the frames."""
    groups = (*TRAINING_GROUPS, "released")
    unknown = np.flatnonzero(~np.isin(found["group"], groups))
    if unknown.size:
        i = unknown[0]
        return f"labels video {i} with group {found['group'][i]!r}; the groups are {', '.join(groups)}"
    return _event_problem(found["event_frame"], frames)


def pair_labels_problem(found: dict[str, np.ndarray], frames: int, custom: bool = False) -> str | None:
    """What is wrong with a test split's labels, or None: every scenario and setting known (a
    hand-made split of `xvoe.custom` names its scenario freely), members 0 and 1 of every pair
    exactly once, member 0 possible and member 1 impossible except in S2, where both are
    possible (in a hand-made split member 1 is the edited, impossible video), event frames
    within the frames."""
    scenario, setting, member = found["scenario"], found["setting"], found["member"]
    # one integer per (scenario, setting) and per pair, so that 10,000 videos cost one Python pass
    codes = {key: code for code, key in enumerate(dict.fromkeys(zip(scenario, setting)))}
    setting_code = np.fromiter((codes[key] for key in zip(scenario, setting)), np.int64, len(scenario))
    for (name, label), code in codes.items():
        i = int(np.argmax(setting_code == code))
        settings = ("S1", "S2", "S3") if custom else SCENARIOS[name].SETTINGS if name in SCENARIOS else None
        if settings is None or not name:
            return f"labels video {i} with scenario {name!r}; the scenarios are {', '.join(SCENARIOS)}"
        if label not in settings:
            return f"labels video {i} {name} {label!r}; {name}'s settings are {', '.join(settings)}"
    odd = np.flatnonzero(~np.isin(member, (0, 1)) | (found["pair"] < 0))
    if odd.size:
        i = odd[0]
        return f"labels video {i} pair {found['pair'][i]} member {member[i]}; pairs count from 0, members are 0 and 1"
    pair_key = setting_code * (int(found["pair"].max(initial=0)) + 1) + found["pair"]
    videos, times = np.unique(pair_key * 2 + member, return_counts=True)
    if np.any(times > 1):
        i, j = np.flatnonzero(pair_key * 2 + member == videos[times > 1][0])[:2]
        return f"labels videos {i} and {j} both {scenario[i]} {setting[i]} pair {found['pair'][i]} member {member[i]}"
    pairs, members = np.unique(pair_key, return_counts=True)
    if np.any(members != 2):
        alone = np.flatnonzero(pair_key == pairs[members != 2][0])[0]
        return (f"labels video {alone} {scenario[alone]} {setting[alone]} pair {found['pair'][alone]}, "
                "which has no other member")
    expected = (member == 0) | ((setting == "S2") & (not custom))
    wrong = np.flatnonzero(found["possible"] != expected)
    if wrong.size:
        i = wrong[0]
        return (f"labels video {i} ({scenario[i]} {setting[i]} member {member[i]}) "
                f"{'possible' if found['possible'][i] else 'impossible'}; member 0 is possible, member 1 is "
                + ("impossible in a hand-made pair" if custom else "possible in S2 only"))
    return _event_problem(found["event_frame"], frames)


def read_frames(file: h5py.File, name: str, start: int, stop: int | None = None) -> np.ndarray:
    """`file[name][start:stop]` (`file[name][start]` without `stop`) of a split's per-video
    frames (`rgbd`, `ids`), or a one-line error naming the file and the first video whose
    chunk cannot be read (damaged on disk) or, for `ids`, whose slot ids run past the split's
    slots: every video is checked where it is read, as `_value_problem` reads only two."""
    try:
        found = file[name][start] if stop is None else file[name][start:stop]
    except OSError:
        rows = range(start, start + 1) if stop is None else range(*slice(start, stop).indices(len(file[name])))
        raise XvoeError(damaged(file.filename, name, _first_unreadable(file[name], rows))) from None
    if name == "ids":
        _check_ids(file, found if stop is not None else found[None], start)
    return found


def _check_ids(file: h5py.File, ids: np.ndarray, start: int) -> None:
    """Refuse slot ids (videos, T, H, W) past the split's slots, naming the first video holding one."""
    slots = file["kind"].shape[1]
    tops = ids.reshape(len(ids), -1).max(axis=1, initial=0)
    if np.any(tops > slots):
        video = int(np.argmax(tops > slots))
        raise XvoeError(f"{file.filename} has slot ids up to {tops[video]} in video {start + video}; they run "
                        f"0..{slots} (0 = background)")


def read_states(file: h5py.File, start: int, stop: int | None = None) -> np.ndarray:
    """`file["states"][start:stop]` (one video's without `stop`), or a one-line error naming
    the first video whose states are NaN or infinite where the schema allows only numbers: an
    import of the released X-VoE (its `source` attribute) has NaN where the release holds no
    state, a generated split has a number everywhere."""
    found = file["states"][start] if stop is None else file["states"][start:stop]
    videos = found if stop is not None else found[None]
    finite = np.isfinite(videos).reshape(len(videos), -1).all(axis=1)
    if "source" not in file.attrs and not finite.all():
        video = start + int(np.argmin(finite))
        raise XvoeError(f"{file.filename} has NaN or infinite states in video {video}; a generated split's "
                        "states are numbers (only an imported release's may be NaN)")
    return found


def _first_unreadable(dataset: h5py.Dataset, rows: range) -> int:
    """The first of `rows` whose chunk cannot be read (each read alone: only on the error's path)."""
    for row in rows:
        try:
            dataset[row]
        except OSError:
            return row
    return rows[0]


def damaged(path: str | os.PathLike, name: str, video: int) -> str:
    """The one line that says a video's stored chunk cannot be read."""
    return (f"{path} is damaged: video {video}'s {name} cannot be read (its stored chunk does not decompress); "
            "generate or copy the split again")


def config_of(file: h5py.File) -> dict:
    return json.loads(file.attrs["config"])


def wall_mask(file: h5py.File, start: int, stop: int) -> np.ndarray:
    """(N, K) bool: the slots of videos [start, stop) that hold a wall, from the kind map."""
    names = list(file.attrs["kind_names"])
    return np.isin(file["kind"][start:stop], [names.index(name) for name in WALL_KINDS if name in names])


def strings(file: h5py.File, name: str) -> np.ndarray:
    """A string label column as a numpy array of str."""
    return file[name].asstr()[:]


def labels(file: h5py.File, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The named label columns of every video, string ones as str (`strings`)."""
    return {name: strings(file, name) if _LABEL_KINDS[name] == "O" else file[name][:] for name in names}
