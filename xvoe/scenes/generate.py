"""Generates a split of the benchmark into an HDF5 file, in parallel and reproducibly.

The work is cut into units (a training video, or a test pair of two videos); each unit
draws every random choice from its own generator, so the output does not depend on the
number of workers or on how the run is sharded. A training video is seeded by (seed, video);
a test pair by (seed, scenario, pair index), the same for every setting of its scenario: the
S1, S2 and S3 pairs of one index show the same scene under different wall timetables, so
settings can be compared pair by pair.
"""
from __future__ import annotations

import multiprocessing
import os
import signal
import sys
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ..domains import COUNT, SEED, Domain, check_config, within
from ..errors import XvoeError
from ..processes import end_with_parent
from ..progress import progress_bar
from ..resources import check_disk, check_memory, check_workers
from . import store
from .render import Video, render
from .scenarios import SCENARIOS, TEST_SETTINGS, TRAINING_GROUPS
from .writer import EncodedVideo, Writer, atomic_file, copy_videos, encode, held_per_video, write_attributes

__all__ = ["GenerateConfig", "unit_rng", "make_unit", "render_unit", "shard_units", "generate", "merge"]

TRAINING_VARIANTS = tuple((group, with_wall) for group in TRAINING_GROUPS for with_wall in (True, False))
_SPLIT_CODE = {"train": 0, "test": 1}


@dataclass(frozen=True)
class GenerateConfig:
    split: str = "train"
    videos: int = within(10_000, COUNT)      # training videos
    pairs: int = within(1_000, COUNT)        # test pairs per setting
    size: int = within(32, Domain(16, 512))    # the default recipe's frames (a test holds the two together)
    frames: int = within(15, Domain(10, 200))
    seed: int = within(0, SEED)

    def __post_init__(self) -> None:
        if self.split not in store.SPLITS:
            raise XvoeError(f"split must be one of {store.SPLITS}, not {self.split!r}")
        check_config(self)

    @property
    def units(self) -> int:
        return self.videos if self.split == "train" else self.pairs * len(TEST_SETTINGS)

    @property
    def videos_per_unit(self) -> int:
        return 1 if self.split == "train" else 2

    def to_dict(self) -> dict:
        data = asdict(self)
        data.pop(data["split"] == "train" and "pairs" or "videos")
        return data


def unit_rng(config: GenerateConfig, unit: int) -> np.random.Generator:
    if config.split == "train":
        key = [config.seed, _SPLIT_CODE["train"], unit]
    else:
        setting_index, pair = divmod(unit, config.pairs)
        key = [config.seed, _SPLIT_CODE["test"], list(SCENARIOS).index(TEST_SETTINGS[setting_index][0]), pair]
    return np.random.default_rng(np.random.SeedSequence(key))


def make_unit(config: GenerateConfig, unit: int) -> list[EncodedVideo]:
    """Simulate, render and compress the video(s) of one unit."""
    return [encode(video, labels) for video, labels in render_unit(config, unit)]


def render_unit(config: GenerateConfig, unit: int) -> list[tuple[Video, dict]]:
    """Simulate and render the video(s) of one unit, each with its labels: at another
    `config.size`, the same scene (xvoe.scenes.display draws figures so)."""
    rng = unit_rng(config, unit)
    if config.split == "train":
        group, with_wall = TRAINING_VARIANTS[rng.integers(len(TRAINING_VARIANTS))]
        take = TRAINING_GROUPS[group](rng, with_wall, config.frames)
        labels = {"group": group, "has_wall": with_wall, "event_frame": take.event_frame}
        return [(render(take.scene, take.trajectory, config.size), labels)]
    setting_index, pair = divmod(unit, config.pairs)
    scenario, setting = TEST_SETTINGS[setting_index]
    takes = SCENARIOS[scenario].test_pair(rng, setting, config.frames)
    return [(render(take.scene, take.trajectory, config.size),
             {"scenario": scenario, "setting": setting, "pair": pair, "member": member,
              "possible": take.possible, "event_frame": take.event_frame})
            for member, take in enumerate(takes)]


def shard_units(config: GenerateConfig, shard: tuple[int, int]) -> range:
    index, count = shard
    if not (count >= 1 and 0 <= index < count):
        raise XvoeError(f"shard must be I/N with 0 <= I < N, not {index}/{count}")
    if count > config.units:
        raise XvoeError(f"cannot cut {config.units} units into {count} shards")
    return range(index * config.units // count, (index + 1) * config.units // count)


def generate(config: GenerateConfig, out: str | Path, workers: int = 1, shard: tuple[int, int] = (0, 1),
             overwrite: bool = False, progress: bool = True) -> Path:
    """Write the split (or one shard of it) to `out`; returns the path."""
    if workers < 1:
        raise XvoeError(f"workers must be at least 1, not {workers}")
    check_workers(workers)
    units = shard_units(config, shard)
    count = len(units) * config.videos_per_unit
    check_memory(count * held_per_video(config.frames), f"a split of {count:,} videos")
    check_disk(count * _least_bytes_per_video(config), out, f"a split of {count:,} videos")
    with atomic_file(out, overwrite) as file:
        write_attributes(file, config.split, config.to_dict(), config.seed)
        if shard != (0, 1):
            file.attrs["shard"] = f"{shard[0]}/{shard[1]}"
            file.attrs["first_unit"] = units.start
        writer = Writer(file, config.split, count, config.frames, config.size)
        bar = progress_bar(total=count, unit="video", desc=f"generate {config.split}", disable=not progress)
        for videos in _map(partial(make_unit, config), units, workers):
            for video in videos:
                writer.add(video)
            bar.update(len(videos))
        bar.close()
        writer.finish()
    return Path(out)


def _least_bytes_per_video(config: GenerateConfig) -> float:
    """What a video surely takes on disk: half of the measured size, about 210 + 8 x size bytes
    a frame (a 15-frame video 7.0 kB at 32 px, 18.4 kB at 128 px; scenes compress differently)."""
    return config.frames * (210 + 8 * config.size) / 2


def _map(function, items: range, workers: int):
    if workers == 1:
        yield from map(function, items)
        return
    chunk = max(1, min(64, len(items) // (workers * 8)))
    with multiprocessing.get_context("fork").Pool(workers, initializer=_worker_follows_parent,
                                                initargs=(os.getpid(),)) as pool:
        yield from pool.imap(function, items, chunksize=chunk)


def _worker_follows_parent(parent: int) -> None:
    """A worker ignores Ctrl-C (the parent stops the pool and removes its half-written file) and
    dies at once when the pool ends it, whatever SIGTERM handler the parent had, or when the
    parent dies (`end_with_parent`); its stderr goes nowhere: a unit's error is raised in the
    parent, and a worker would only print the pool's broken pipe once the parent is killed."""
    end_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    sys.stderr = open(os.devnull, "w")    # noqa: SIM115 - open for the worker's whole life


def merge(parts: list[str | Path], out: str | Path, overwrite: bool = False, progress: bool = True) -> Path:
    """Join the shards of one run into the file an unsharded run would have written."""
    if not parts:
        raise XvoeError("merge needs at least one shard file")
    files = [store.open_dataset(p) for p in parts]
    try:
        shards = sorted(((_shard_of(path, file), str(path), file) for path, file in zip(parts, files)),
                        key=lambda shard: shard[0])
        first = shards[0][2]
        count = shards[0][0][1]
        for (_, shard_count), path, file in shards:
            if file.attrs["config"] != first.attrs["config"] or shard_count != count:
                raise XvoeError(f"{path} belongs to another run (its config or shard count differs)")
        found = [index for (index, _), _, _ in shards]
        if found != list(range(count)):
            raise XvoeError(f"shards {found} do not make up 0..{count - 1} exactly once")
        config = GenerateConfig(**store.config_of(first))
        total = sum(file["rgbd"].shape[0] for _, _, file in shards)
        with atomic_file(out, overwrite) as target:
            write_attributes(target, config.split, config.to_dict(), config.seed)
            writer = Writer(target, config.split, total, config.frames, config.size)
            for _, _, file in progress_bar(shards, desc="merge", unit="shard", disable=not progress):
                copy_videos(file, writer)
            writer.finish()
    finally:
        for file in files:
            file.close()
    return Path(out)


def _shard_of(path, file) -> tuple[int, int]:
    if "shard" not in file.attrs:
        raise XvoeError(f"{path} is not a shard (it was not written with --shard)")
    try:
        index, count = (int(v) for v in str(file.attrs["shard"]).split("/"))
    except ValueError:
        raise XvoeError(f"{path} has a shard attribute {file.attrs['shard']!r}, not I/N") from None
    return index, count
