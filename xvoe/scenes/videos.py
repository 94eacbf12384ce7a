"""Finding, describing and redrawing videos of an open split file.

The label lookups every verb needs (is an index there, which pair is it in, what does it
show) and the ground truth drawn from the saved states, for comparing with what a model
believes.
"""
from __future__ import annotations

import h5py
import numpy as np

from ..errors import XvoeError
from . import store
from .world import FLOOR, WORLD

__all__ = ["check_index", "video_indices", "describe", "find_pair", "pair_rows", "labels_of", "list_videos",
           "wall_lowered", "true_objects", "silhouette"]


def check_index(file: h5py.File, index: int) -> None:
    """An error unless `index` names a video of the split file."""
    count = file["rgbd"].shape[0]
    if not 0 <= index < count:
        raise XvoeError(f"index {index} is out of range: the file holds videos 0..{count - 1}")


def video_indices(file: h5py.File, index: int) -> list[int]:
    """The videos to show for `index`: its whole pair in a test file, itself otherwise."""
    check_index(file, index)
    if file.attrs["split"] == "test":
        first = index - int(file["member"][index])
        return [first, first + 1]
    return [index]


def describe(file: h5py.File, index: int) -> str:
    if file.attrs["split"] == "test":
        label = "possible" if file["possible"][index] else "impossible"
        return (f"{file['scenario'].asstr()[index]} {file['setting'].asstr()[index]} "
                f"pair {file['pair'][index]} member {file['member'][index]} ({label})")
    has_wall = "with wall" if file["has_wall"][index] else "no wall"
    return f"train video {index}: {file['group'].asstr()[index]}, {has_wall}"


def find_pair(file: h5py.File, scenario: str, setting: str, pair: int) -> tuple[int, int]:
    """The video indices of member 0 and member 1 of a test pair, or a one-line error naming
    what the file holds."""
    if file.attrs["split"] != "test":
        raise XvoeError(f"{file.filename} is a {file.attrs['split']} split; pairs live in test splits")
    return pair_rows(store.strings(file, "scenario"), store.strings(file, "setting"), file["pair"][:],
                      file["member"][:], scenario, setting, pair, str(file.filename))


_VIDEO_FIELDS = ("index", "scenario", "setting", "pair", "member", "possible")


def list_videos(file: h5py.File, scenario: str | None = None, setting: str | None = None,
                member: int | None = None, pair: int | None = None) -> list[dict]:
    """The videos of a test split, one row each (VIDEO_FIELDS), those of `scenario`, `setting`,
    `member` and `pair` where given, in index order: how a notebook or `xvoe list` picks videos
    instead of counting indices by hand. A filter naming what the split does not hold is a
    one-line error that says what it holds."""
    if file.attrs["split"] != "test":
        raise XvoeError(f"{file.filename} is a {file.attrs['split']} split; pairs live in test splits")
    found = store.labels(file, _VIDEO_FIELDS[1:])
    chosen, so_far = np.ones(len(found["scenario"]), bool), []
    for name, wanted in (("scenario", scenario), ("setting", setting), ("member", member), ("pair", pair)):
        if wanted is None:
            continue
        held = list(dict.fromkeys(found[name][chosen].tolist()))
        if wanted not in held:
            among = f" among its {', '.join(so_far)} videos" if so_far else ""
            raise XvoeError(f"{file.filename} holds no {name} {wanted!r}{among}; it holds {_held(held)}")
        chosen &= found[name] == wanted
        so_far.append(str(wanted) if name in ("scenario", "setting") else f"{name} {wanted}")
    return [{"index": int(i), "scenario": str(found["scenario"][i]), "setting": str(found["setting"][i]),
             "pair": int(found["pair"][i]), "member": int(found["member"][i]), "possible": bool(found["possible"][i])}
            for i in np.flatnonzero(chosen)]


def _held(values: list) -> str:
    """What a label column holds, in a line: names listed, a run of numbers as its range."""
    if values and all(isinstance(v, int) for v in values):
        return f"{min(values)}..{max(values)}" if len(values) > 2 else " and ".join(map(str, sorted(values)))
    return ", ".join(map(str, values))


def pair_rows(scenarios, settings, pairs, members, scenario: str, setting: str, pair: int,
              where: str) -> tuple[int, int]:
    """Rows of member 0 and 1 of (scenario, setting, pair) among label columns."""
    scenarios, settings = np.asarray(scenarios).astype(str), np.asarray(settings).astype(str)
    known = list(dict.fromkeys(scenarios))
    if scenario not in known:
        raise XvoeError(f"{where} holds no scenario {scenario!r}; it holds {', '.join(known)}")
    held = list(dict.fromkeys(settings[scenarios == scenario]))
    if setting not in held:
        raise XvoeError(f"{where} holds no setting {setting!r} of {scenario}; it holds {', '.join(held)}")
    chosen = (scenarios == scenario) & (settings == setting)
    pairs, members = np.asarray(pairs).astype(int), np.asarray(members).astype(int)
    rows = [np.flatnonzero(chosen & (pairs == pair) & (members == m)) for m in (0, 1)]
    if any(len(r) != 1 for r in rows):
        have = np.unique(pairs[chosen])
        raise XvoeError(f"{where} holds no pair {pair} of {scenario} {setting}; its pairs are "
                        f"{have.min()}..{have.max()}")
    return int(rows[0][0]), int(rows[1][0])


def labels_of(file: h5py.File, index: int) -> tuple[str, str, int]:
    """The (scenario, setting, pair) video `index` of an open split is labelled with."""
    return file["scenario"].asstr()[index], file["setting"].asstr()[index], int(file["pair"][index])


def wall_lowered(file: h5py.File, index: int) -> np.ndarray:
    """How far the wall is lowered into view at each frame (T,) of video `index`, from its saved
    states: 1 where a wall stands on the floor, 0 where it is lifted out of the picture or
    there is none (with several walls, the lowest)."""
    walls = np.flatnonzero(store.wall_mask(file, index, index + 1)[0])
    frames, size = file["rgbd"].shape[1], file["rgbd"].shape[2]
    if walls.size == 0:
        return np.zeros(frames)
    columns = list(file["states"].attrs["state_columns"])
    states = store.read_states(file, index)[:, walls]
    bottom = states[..., columns.index("y")] + states[..., columns.index("height")] / 2   # pixels, y down
    raised = (size - bottom) * (WORLD / size) - FLOOR           # world units above the floor
    lowered = np.clip(1.0 - raised / (WORLD - FLOOR), 0.0, 1.0)
    lowered = np.where(states[..., columns.index("present")] > 0, np.round(lowered, 6), 0.0)
    return lowered.max(axis=1)


def true_objects(file: h5py.File, index: int) -> np.ndarray:
    """The ground truth without the wall: each ball and cube of video `index` drawn from its
    saved states in its own colour on white, hidden or not (T, H, W, 4) uint8, the last
    channel 255 (far). Objects overlapping each other are drawn in slot order."""
    names = list(file.attrs["kind_names"])
    columns = list(file["states"].attrs["state_columns"])
    frames, size = file["rgbd"].shape[1], file["rgbd"].shape[2]
    states, colors = store.read_states(file, index), file["color"][index]
    picture = np.full((frames, size, size, 4), 255, np.uint8)
    for slot, kind in enumerate(file["kind"][index]):
        if names[kind] in ("ball", "cube"):
            picture[..., :3][silhouette(states[:, slot], columns, names[kind], size)] = colors[slot]
    return picture


def silhouette(states: np.ndarray, columns: list[str], kind: str, size: int) -> np.ndarray:
    """The whole silhouette (T, H, W) of one object from its saved states (T, S), occlusion
    ignored: a disk for a ball, a square for a cube."""
    x, y, half = (states[:, columns.index(c)] for c in ("x", "y", "size"))
    centres = np.arange(size) + 0.5
    dx = centres[None, None, :] - x[:, None, None]
    dy = centres[None, :, None] - y[:, None, None]
    if kind == "ball":
        mask = dx ** 2 + dy ** 2 <= half[:, None, None] ** 2
    else:
        mask = (np.abs(dx) <= half[:, None, None]) & (np.abs(dy) <= half[:, None, None])
    return mask & (states[:, columns.index("present")] > 0)[:, None, None]
