"""`xvoe import`: the paper's released X-VoE TFRecords into xvoe's HDF5 schema, without TensorFlow.

What the release holds is read off the reference code (daibopku/X-VoE): `build_data/video_read.py`
names the files (test/SCENARIO/eval-part-NNN.tfrecord, six per scenario and four for permanence;
train/train-part-NNN.tfrecord) and the features of a record (`raw_image` and `mask`, each a
serialized uint8 tensor, and a float list `slot`); `utils/metrix_ds.py` and `eval/eval_xpl.py` say
how a scenario's test videos are laid out (blocks, below). The facts and what is assumed beyond
them: docs/benchmark.md, "The released X-VoE and this one".
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import XvoeError
from ..outputs import claim_file, claim_scope
from ..progress import progress_bar
from . import store
from .render import STATE_COLUMNS
from .scenes import SCENARIOS
from .tfrecord import TFRecordError, parse_example, parse_tensor, records
from .world import KIND_NAMES, MAX_SLOTS

# The reference's test blocks in record order (eval/eval_xpl.py batches a scenario's records by
# 1000; utils/metrix_ds.py compares block 0 with 1, 2 with 3, 4 with 5 and counts 1 and 5 impossible)
BLOCKS = (("S1", 0, True), ("S1", 1, False), ("S2", 0, True), ("S2", 1, True), ("S3", 0, True), ("S3", 1, False))
TEST_FILES = {"collision": 6, "blocking": 6, "permanence": 4, "continuity": 6}    # build_data/video_read.py
FEATURES = ("raw_image", "mask")
OCCLUDER_SLOT = 7            # eval/eval_xpl.py leaves the last of the 8 slots out of the dynamics term
IMPORTED_KINDS = (*KIND_NAMES, "object")      # a seen slot whose shape the masks do not tell
SOURCE_NAME = "X-VoE release (TFRecord)"


@dataclass(frozen=True)
class Part:
    """One scenario's test files (or the training files), in the order their records count."""

    scenario: str | None
    files: tuple[Path, ...]


@claim_scope()
def import_released(source: str | os.PathLike, split: str, out: str | os.PathLike, *, overwrite: bool = False,
                    progress: bool = True) -> Path:
    """Write the released split under `source` (the downloaded X-VoE directory, with test/ and
    train/) to `out` in xvoe's schema. Every file is read through once first, so a truncated or
    foreign file is refused before anything is written."""
    if split not in store.SPLITS:
        raise XvoeError(f"--split must be train or test, not {split!r}")
    claim_file(out, overwrite)
    parts = _test_parts(Path(source)) if split == "test" else [_train_part(Path(source))]
    counts, first = _survey(parts)
    frames, size = first[0].shape[:2]
    total = sum(counts)
    per_block = {part.scenario: count // TEST_FILES[part.scenario] for part, count in zip(parts, counts)} \
        if split == "test" else {}
    config = {"source": SOURCE_NAME, "split": split, "frames": int(frames), "size": int(size),
              "files": [str(path.relative_to(Path(source))) for part in parts for path in part.files],
              **({"pairs": per_block} if split == "test" else {"videos": total})}
    with store.atomic_file(out, overwrite) as file:
        _write_attributes(file, split, config)
        writer = store.Writer(file, split, total, int(frames), int(size))
        bar = progress_bar(total=total, unit="video", desc=f"import {split}", disable=not progress)
        offset = 0
        for part, count in zip(parts, counts):
            for index, (image, masks) in enumerate(_videos(part, (frames, size))):
                at = offset + _test_row(index, per_block[part.scenario]) if split == "test" else offset + index
                labels = _test_labels(part.scenario, index, per_block[part.scenario]) if split == "test" \
                    else _train_labels(masks)
                writer.add(store.encode(_as_video(image, masks), labels), at=at)
                bar.update()
            offset += count
        bar.close()
        writer.finish()
    return Path(out)


def _test_parts(source: Path) -> list[Part]:
    """The scenarios present under source/test (or source itself), each with all its files."""
    root = source / "test" if (source / "test").is_dir() else source
    if not root.is_dir():
        raise XvoeError(f"{source} is not a directory; give the downloaded X-VoE directory (with test/ inside)")
    parts = []
    for scenario in SCENARIOS:
        if not (root / scenario).is_dir():
            continue
        files = tuple(root / scenario / f"eval-part-{i:03d}.tfrecord" for i in range(TEST_FILES[scenario]))
        missing = [str(path) for path in files if not path.is_file()]
        if missing:
            raise XvoeError(f"{scenario} is incomplete: {missing[0]} is missing ({len(missing)} of {len(files)} files)")
        parts.append(Part(scenario, files))
    if not parts:
        raise XvoeError(f"{root} holds none of the test scenarios' directories ({', '.join(TEST_FILES)})")
    return parts


def _train_part(source: Path) -> Part:
    root = source / "train" if (source / "train").is_dir() else source
    files = tuple(sorted(root.glob("train-part-[0-9][0-9][0-9].tfrecord")))
    if not files:
        raise XvoeError(f"{root} holds no train-part-NNN.tfrecord file")
    return Part(None, files)


def _survey(parts: list[Part]) -> tuple[list[int], tuple[np.ndarray, np.ndarray]]:
    """Records per part, every checksum checked and each file's first record parsed, and the
    first video (its shape is the split's); refuses what cannot be imported whole."""
    counts, first = [], None
    for part in parts:
        count = 0
        for path in part.files:
            found = 0
            for record in records(path):
                if found == 0:
                    video = _parse(record, path, 0)
                    first = video if first is None else first
                    _check_same_shape(video, first, path, 0)
                found += 1
            count += found
        if part.scenario is not None:
            _check_blocks(part, count)
        counts.append(count)
    if first is None:
        raise XvoeError("the files hold no record")
    return counts, first


def _check_blocks(part: Part, count: int) -> None:
    blocks = TEST_FILES[part.scenario]
    if count == 0 or count % blocks:
        raise XvoeError(f"{part.scenario} holds {count} videos, not {blocks} equal blocks (one per setting and "
                        "member, as the reference's metrics read them)")


def _parse(record: bytes, path: Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(image (T, H, W, 4), masks (T, K, H, W)) of one record, or a one-line error."""
    where = f"{path}, record {index}"
    try:
        example = parse_example(record)
    except TFRecordError as error:
        raise TFRecordError(f"{where}: {error}") from None
    missing = [name for name in FEATURES if len(example.get(name, ())) != 1]
    if missing:
        raise TFRecordError(f"{where} is not an X-VoE video: no {' or '.join(missing)} feature "
                            f"(it has {', '.join(sorted(example)) or 'none'})")
    try:
        image, masks = (parse_tensor(example[name][0]) for name in FEATURES)
    except TFRecordError as error:
        raise TFRecordError(f"{where}: {error}") from None
    if masks.ndim == 5 and masks.shape[-1] == 1:
        masks = masks[..., 0]
    _check_video(image, masks, where)
    return image, masks


def _check_video(image: np.ndarray, masks: np.ndarray, where: str) -> None:
    if image.dtype != np.uint8 or image.ndim != 4 or image.shape[1] != image.shape[2]:
        raise TFRecordError(f"{where}: raw_image is {image.dtype} {image.shape}, not uint8 (T, H, H, 4)")
    if image.shape[3] == 3:
        raise TFRecordError(f"{where}: raw_image is RGB without depth; xvoe's frames are RGBD and the depth "
                            "cannot be made up")
    if image.shape[3] != 4:
        raise TFRecordError(f"{where}: raw_image has {image.shape[3]} channels, not 4 (RGB and depth)")
    frames, size = image.shape[:2]
    if masks.dtype != np.uint8 or masks.ndim != 4 or (masks.shape[0], *masks.shape[2:]) != (frames, size, size):
        raise TFRecordError(f"{where}: mask is {masks.dtype} {masks.shape}, not uint8 ({frames}, K, {size}, {size})")
    if masks.shape[1] > MAX_SLOTS:
        raise TFRecordError(f"{where}: mask has {masks.shape[1]} slots; the xvoe schema holds {MAX_SLOTS}")


def _check_same_shape(video, first, path: Path, index: int) -> None:
    if video[0].shape != first[0].shape:
        raise TFRecordError(f"{path}, record {index}: frames of {video[0].shape}, unlike the first video's "
                            f"{first[0].shape}; one file holds one size")


def _videos(part: Part, shape: tuple[int, int]):
    """Every (image, masks) of a part, in record order."""
    for path in part.files:
        for index, record in enumerate(records(path)):
            video = _parse(record, path, index)
            if video[0].shape[:2] != shape:
                raise TFRecordError(f"{path}, record {index}: {video[0].shape[0]} frames of "
                                    f"{video[0].shape[1]} px, unlike the first video's {shape[0]} of {shape[1]}")
            yield video


def _test_row(index: int, pairs: int) -> int:
    """Where the index-th video of a scenario's records goes among that scenario's rows: the
    schema's order is setting by setting, pair by pair, member 0 then 1."""
    block, pair = divmod(index, pairs)
    setting, member = divmod(block, 2)
    return (setting * pairs + pair) * 2 + member


def _test_labels(scenario: str, index: int, pairs: int) -> dict:
    block, pair = divmod(index, pairs)
    setting, member, possible = BLOCKS[block]
    # the release records no event frame: -1, as for a pair without one
    return {"scenario": scenario, "setting": setting, "pair": pair, "member": member, "possible": possible,
            "event_frame": -1}


def _train_labels(masks: np.ndarray) -> dict:
    has_wall = masks.shape[1] > OCCLUDER_SLOT and bool(masks[:, OCCLUDER_SLOT].any())
    return {"group": "released", "has_wall": has_wall, "event_frame": -1}


@dataclass
class _Video:
    """What store.encode reads of a rendered video."""

    rgbd: np.ndarray
    ids: np.ndarray
    states: np.ndarray
    kind: np.ndarray
    color: np.ndarray


def ids_of(masks: np.ndarray) -> np.ndarray:
    """(T, H, W) slot ids from (T, K, H, W) per-slot masks: k+1 where slot k's mask is set, 0 where
    none is; where masks overlap, the lowest slot (the release's masks are of what is seen, so
    they should not overlap)."""
    seen = masks > 0
    return np.where(seen.any(axis=1), seen.argmax(axis=1) + 1, 0).astype(np.uint8)


def _as_video(image: np.ndarray, masks: np.ndarray) -> _Video:
    """A video in the schema: the image as rgbd, ids from the masks, and of the states, kinds and
    colours what the masks tell (the rest NaN: the release holds no states)."""
    frames, slots = masks.shape[:2]
    seen = masks > 0
    pixels = seen.sum(axis=(2, 3))                               # (T, K)
    states = np.full((frames, MAX_SLOTS, len(STATE_COLUMNS)), np.nan, np.float32)
    column = {name: i for i, name in enumerate(STATE_COLUMNS)}
    ever = np.zeros(MAX_SLOTS, bool)
    ever[:slots] = pixels.any(axis=0)
    states[..., column["present"]] = ever[None, :]
    visible = np.zeros((frames, MAX_SLOTS), np.float32)
    visible[:, :slots] = pixels > 0
    states[..., column["visible"]] = visible
    rows, cols = np.arange(image.shape[1], dtype=np.float64), np.arange(image.shape[2], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):        # NaN where a slot shows nothing
        states[:, :slots, column["x"]] = (seen.sum(axis=2) * cols).sum(axis=-1) / pixels
        states[:, :slots, column["y"]] = (seen.sum(axis=3) * rows).sum(axis=-1) / pixels
    kind = np.zeros(MAX_SLOTS, np.int8)
    kind[ever] = IMPORTED_KINDS.index("object")
    if ever[OCCLUDER_SLOT]:
        kind[OCCLUDER_SLOT] = IMPORTED_KINDS.index("wall")
    color = np.zeros((MAX_SLOTS, 3), np.uint8)
    for k in np.flatnonzero(ever):
        color[k] = np.round(image[..., :3][seen[:, k]].mean(axis=0)).astype(np.uint8)
    return _Video(np.ascontiguousarray(image), ids_of(masks), states, kind, color)


def _write_attributes(file: h5py.File, split: str, config: dict) -> None:
    """The schema's attributes; what the release does not record (its seed, its depth scale) is -1 or NaN."""
    store.write_attributes(file, split, config, -1)
    file.attrs["generator_version"] = f"import of the {SOURCE_NAME}"
    file.attrs["kind_names"] = list(IMPORTED_KINDS)
    file.attrs["depth_far"] = np.nan
    file.attrs["source"] = SOURCE_NAME
