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
import warnings
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import XvoeError
from ..outputs import claim_file, claim_scope
from ..progress import progress_bar
from . import store
from .render import STATE_COLUMNS
from .scenarios import SCENARIOS
from .tfrecord import TFRecordError, parse_example, parse_tensor, records
from .world import KIND_NAMES, MAX_SLOTS
from .writer import Writer, atomic_file, encode, write_attributes

__all__ = ["SOURCE_NAME", "import_released"]

# The reference's test blocks in record order (eval/eval_xpl.py batches a scenario's records by
# 1000; utils/metrix_ds.py compares block 0 with 1, 2 with 3, 4 with 5 and counts 1 and 5 impossible)
_BLOCKS = (("S1", 0, True), ("S1", 1, False), ("S2", 0, True), ("S2", 1, True), ("S3", 0, True), ("S3", 1, False))
_TEST_FILES = {"collision": 6, "blocking": 6, "permanence": 4, "continuity": 6}    # build_data/video_read.py
_FEATURES = ("raw_image", "mask")
_OCCLUDER_SLOT = 7            # eval/eval_xpl.py leaves the last of the 8 slots out of the dynamics term
_IMPORTED_KINDS = (*KIND_NAMES, "object")      # a seen slot whose shape the masks do not tell
SOURCE_NAME = "X-VoE release (TFRecord)"


@dataclass(frozen=True)
class _Part:
    """One scenario's test files (or the training files), in the order their records count."""

    scenario: str | None
    files: tuple[Path, ...]


@claim_scope()
def import_released(source: str | os.PathLike, split: str, out: str | os.PathLike, *, size: int | None = None,
                    overwrite: bool = False, progress: bool = True) -> Path:
    """Write the released split under `source` (the downloaded X-VoE directory, with test/ and
    train/) to `out` in xvoe's schema, at `size` pixels a side if given (a divisor of the
    release's 128, so that the shipped 32x32 models read it; see `_downsample`). Every file is
    read through once first, so a truncated or foreign file is refused before anything is written."""
    if split not in store.SPLITS:
        raise XvoeError(f"--split must be train or test, not {split!r}")
    claim_file(out, overwrite)
    parts = _test_parts(Path(source)) if split == "test" else [_train_part(Path(source))]
    counts, first = _survey(parts)
    frames, native = first[0].shape[:2]
    size = _check_size(size, native)
    total = sum(counts)
    per_block = {part.scenario: count // _TEST_FILES[part.scenario] for part, count in zip(parts, counts)} \
        if split == "test" else {}
    config = {"source": SOURCE_NAME, "split": split, "frames": int(frames), "size": size,
              "files": [str(path.relative_to(Path(source))) for part in parts for path in part.files],
              **({"source_size": int(native), "resampled": _RESAMPLING} if size != native else {}),
              **({"pairs": per_block} if split == "test" else {"videos": total})}
    overlapped = 0
    with atomic_file(out, overwrite) as file:
        _write_attributes(file, split, config)
        writer = Writer(file, split, total, int(frames), size)
        bar = progress_bar(total=total, unit="video", desc=f"import {split}", disable=not progress)
        offset = 0
        for part, count in zip(parts, counts):
            for index, (image, masks) in enumerate(_videos(part, (frames, native))):
                at = offset + _test_row(index, per_block[part.scenario]) if split == "test" else offset + index
                labels = _test_labels(part.scenario, index, per_block[part.scenario]) if split == "test" \
                    else _train_labels(masks)
                ids, shared = _ids_of(masks, image[..., 3])
                overlapped += shared
                if size != native:
                    image, ids = _downsample(image, ids, size)
                writer.add(encode(_as_video(image, ids), labels), at=at)
                bar.update()
            offset += count
        bar.close()
        writer.finish()
    if overlapped:
        warnings.warn(f"{overlapped} pixels lie under more than one slot's mask (amodal masks); each went to the "
                      "nearest of its slots by depth", stacklevel=2)
    return Path(out)


def _check_size(size: int | None, native: int) -> int:
    """The size to store: the release's own, or a divisor of it (every output pixel a whole block)."""
    if size is None or size == native:
        return int(native)
    if not 0 < size < native or native % size:
        raise XvoeError(f"--size {size} does not divide the release's {native}x{native} frames; give a divisor "
                        f"of {native} (e.g. 32, the shipped models' size)")
    return int(size)


def _test_parts(source: Path) -> list[_Part]:
    """The scenarios present under source/test (or source itself), each with all its files."""
    root = source / "test" if (source / "test").is_dir() else source
    if not root.is_dir():
        raise XvoeError(f"{source} is not a directory; give the downloaded X-VoE directory (with test/ inside)")
    parts = []
    for scenario in SCENARIOS:
        if not (root / scenario).is_dir():
            continue
        files = tuple(root / scenario / f"eval-part-{i:03d}.tfrecord" for i in range(_TEST_FILES[scenario]))
        missing = [str(path) for path in files if not path.is_file()]
        if missing:
            raise XvoeError(f"{scenario} is incomplete: {missing[0]} is missing ({len(missing)} of {len(files)} files)")
        parts.append(_Part(scenario, files))
    if not parts:
        raise XvoeError(f"{root} holds none of the test scenarios' directories ({', '.join(_TEST_FILES)})")
    return parts


def _train_part(source: Path) -> _Part:
    root = source / "train" if (source / "train").is_dir() else source
    files = tuple(sorted(root.glob("train-part-[0-9][0-9][0-9].tfrecord")))
    if not files:
        raise XvoeError(f"{root} holds no train-part-NNN.tfrecord file")
    numbers = {int(path.name[len("train-part-"):][:3]) for path in files}
    gaps = sorted(set(range(max(numbers) + 1)) - numbers)
    if gaps:
        warnings.warn(f"the training set is incomplete: {len(files)} files, without "
                      f"{', '.join(f'train-part-{n:03d}' for n in gaps[:3])}{' ...' if len(gaps) > 3 else ''} "
                      f"({len(gaps)} missing up to train-part-{max(numbers):03d}); the files present are imported",
                      stacklevel=3)
    return _Part(None, files)


def _survey(parts: list[_Part]) -> tuple[list[int], tuple[np.ndarray, np.ndarray]]:
    """Records per part, every checksum checked and each file's first record parsed, and the
    first video (its shape is the split's); refuses what cannot be imported whole."""
    counts, first = [], None
    for part in parts:
        count, per_file = 0, []
        for path in part.files:
            found = 0
            for record in records(path):
                if found == 0:
                    video = _parse(record, path, 0)
                    first = video if first is None else first
                    _check_same_shape(video, first, path, 0)
                found += 1
            count += found
            per_file.append(found)
        if part.scenario is not None:
            _check_blocks(part, count)
            _check_files(part, per_file)
        counts.append(count)
    if first is None:
        raise XvoeError("the files hold no record")
    return counts, first


def _check_blocks(part: _Part, count: int) -> None:
    blocks = _TEST_FILES[part.scenario]
    if count == 0 or count % blocks:
        raise XvoeError(f"{part.scenario} holds {count} videos, not {blocks} equal blocks (one per setting and "
                        "member, as the reference's metrics read them)")


def _check_files(part: _Part, per_file: list[int]) -> None:
    """Warn where a scenario's files do not each hold one block: the labels go by position
    among the scenario's records, which is what the reference's metrics read, but such files
    were not written as the reference's build scripts write them."""
    block = sum(per_file) // _TEST_FILES[part.scenario]
    if any(found != block for found in per_file):
        warnings.warn(f"{part.scenario}'s files hold {', '.join(map(str, per_file))} records, not one block of "
                      f"{block} each; the records are labelled by their place among the scenario's "
                      f"{sum(per_file)} (blocks of {block}), not by file", stacklevel=4)


def _parse(record: bytes, path: Path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(image (T, H, W, 4), masks (T, K, H, W)) of one record, or a one-line error."""
    where = f"{path}, record {index}"
    try:
        example = parse_example(record)
    except TFRecordError as error:
        raise TFRecordError(f"{where}: {error}") from None
    missing = [name for name in _FEATURES if len(example.get(name, ())) != 1]
    if missing:
        raise TFRecordError(f"{where} is not an X-VoE video: no {' or '.join(missing)} feature "
                            f"(it has {', '.join(sorted(example)) or 'none'})")
    try:
        image, masks = (parse_tensor(example[name][0]) for name in _FEATURES)
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


def _videos(part: _Part, shape: tuple[int, int]):
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
    setting, member, possible = _BLOCKS[block]
    # the release records no event frame: -1, as for a pair without one
    return {"scenario": scenario, "setting": setting, "pair": pair, "member": member, "possible": possible,
            "event_frame": -1}


def _train_labels(masks: np.ndarray) -> dict:
    has_wall = masks.shape[1] > _OCCLUDER_SLOT and bool(masks[:, _OCCLUDER_SLOT].any())
    return {"group": "released", "has_wall": has_wall, "event_frame": -1}


@dataclass
class _Video:
    """What writer.encode reads of a rendered video."""

    rgbd: np.ndarray
    ids: np.ndarray
    states: np.ndarray
    kind: np.ndarray
    color: np.ndarray


def _ids_of(masks: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, int]:
    """(T, H, W) slot ids from (T, K, H, W) per-slot masks and the (T, H, W) depth (near small):
    k+1 where slot k's mask alone is set, 0 where none is; and the number of pixels under more
    than one mask. The release does not say whether its masks are of what is seen or amodal
    (whole objects, a hidden part included); where they overlap, the nearest slot owns the
    pixel, the slot's depth in a frame being the mean depth of the pixels it alone claims there
    (a slot that claims none alone is behind the others: it loses; ties to the lowest slot)."""
    seen = masks > 0
    claims = seen.sum(axis=1)
    ids = np.where(claims > 0, seen.argmax(axis=1) + 1, 0).astype(np.uint8)
    shared = claims > 1
    if not shared.any():
        return ids, 0
    frames, slots = seen.shape[:2]
    alone = (seen & ~shared[:, None]).reshape(frames, slots, -1)
    pixels = alone.sum(axis=2)
    total = np.matmul(alone.astype(np.float32), depth.reshape(frames, -1, 1).astype(np.float32))[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        slot_depth = np.where(pixels > 0, total / pixels, np.inf)                   # (T, K)
    frame = np.nonzero(shared)[0]
    candidates = np.moveaxis(seen, 1, -1)[shared]                                   # (pixels, K)
    ids[shared] = np.where(candidates, slot_depth[frame], np.inf).argmin(axis=1) + 1
    return ids, int(shared.sum())


# how `_downsample` resamples, recorded in the file's config
_RESAMPLING = "rgb: block mean; ids: the label covering most of a block, ties to the nearer, and a slot a frame " \
             "shows that would own no block takes the block it covers most; depth: the mean of the owner's pixels"


def _downsample(image: np.ndarray, ids: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(T, H, W, 4) RGBD and (T, H, W) ids to `size` pixels a side, H a multiple of it.

    RGB is the block's mean (area averaging). Each block gets one label: the one covering most
    of its pixels, a tie going to the nearer; a slot that a frame shows but that owns no block
    then (an object smaller than a block, or straddling four) takes the block it covers most, so
    that nothing seen at full size vanishes from the ids. Depth is the mean depth of the owner's
    pixels in the block, so that an object's depth is not blended with the wall's or the
    background's at its edges."""
    frames, native = image.shape[:2]
    factor = native // size
    shaped = image.reshape(frames, size, factor, size, factor, 4)
    rgb = np.rint(shaped[..., :3].mean(axis=(2, 4), dtype=np.float64)).astype(np.uint8)
    # every full-size pixel's block (frame, row, column) and label, counted in one bincount each
    block = (np.arange(frames)[:, None, None] * size + np.arange(native)[None, :, None] // factor) * size \
        + np.arange(native)[None, None, :] // factor
    labels = int(ids.max()) + 1
    key = (block * labels + ids).ravel()
    count = frames * size * size * labels
    cover = np.bincount(key, minlength=count).reshape(frames, size, size, labels)
    depth_sum = np.bincount(key, image[..., 3].ravel().astype(np.float64), count).reshape(cover.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        label_depth = np.where(cover > 0, depth_sum / cover, np.inf)
    # most coverage first; among equals the smallest depth (a depth is below 256: one pixel more wins)
    owner = np.argmax(cover * 256.0 - np.minimum(label_depth, 255.0), axis=-1)
    shown = cover[..., 1:].any(axis=(1, 2))                                      # (T, L-1)
    kept = (owner[..., None] == np.arange(1, labels)).any(axis=(1, 2))
    for frame, slot in zip(*np.nonzero(shown & ~kept)):
        at = np.unravel_index(np.argmax(cover[frame, ..., slot + 1]), (size, size))
        owner[(frame, *at)] = slot + 1
    owned = np.take_along_axis(label_depth, owner[..., None], axis=-1)[..., 0]
    rgbd = np.concatenate([rgb, np.rint(owned).astype(np.uint8)[..., None]], axis=-1)
    return rgbd, owner.astype(np.uint8)


def _as_video(image: np.ndarray, ids: np.ndarray) -> _Video:
    """A video in the schema: the image as rgbd, the ids, and of the states, kinds and colours
    what the ids tell (the rest NaN: the release holds no states)."""
    frames = ids.shape[0]
    seen = ids[:, None] == np.arange(1, MAX_SLOTS + 1)[None, :, None, None]   # (T, K, H, W)
    pixels = seen.sum(axis=(2, 3))                               # (T, K)
    states = np.full((frames, MAX_SLOTS, len(STATE_COLUMNS)), np.nan, np.float32)
    column = {name: i for i, name in enumerate(STATE_COLUMNS)}
    ever = pixels.any(axis=0)
    states[..., column["present"]] = ever[None, :]
    states[..., column["visible"]] = pixels > 0
    rows, cols = np.arange(image.shape[1], dtype=np.float64), np.arange(image.shape[2], dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):        # NaN where a slot shows nothing
        states[..., column["x"]] = (seen.sum(axis=2) * cols).sum(axis=-1) / pixels
        states[..., column["y"]] = (seen.sum(axis=3) * rows).sum(axis=-1) / pixels
    kind = np.zeros(MAX_SLOTS, np.int8)
    kind[ever] = _IMPORTED_KINDS.index("object")
    if ever[_OCCLUDER_SLOT]:
        kind[_OCCLUDER_SLOT] = _IMPORTED_KINDS.index("wall")
    color = np.zeros((MAX_SLOTS, 3), np.uint8)
    for k in np.flatnonzero(ever):
        color[k] = np.round(image[..., :3][seen[:, k]].mean(axis=0)).astype(np.uint8)
    return _Video(np.ascontiguousarray(image), ids, states, kind, color)


def _write_attributes(file: h5py.File, split: str, config: dict) -> None:
    """The schema's attributes; what the release does not record (its seed, its depth scale) is -1 or NaN."""
    write_attributes(file, split, config, -1)
    file.attrs["generator_version"] = f"import of the {SOURCE_NAME}"
    file.attrs["kind_names"] = list(_IMPORTED_KINDS)
    file.attrs["depth_far"] = np.nan
    file.attrs["source"] = SOURCE_NAME
