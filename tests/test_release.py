"""The paper's released test set, imitated in its own format, scored by a shipped model: a
128x128 release with amodal masks and a scenario whose files do not each hold one block
imports at 32x32 (`xvoe import --size 32`, a warning line for each), `xvoe score --model xpl`
and `xvoe metrics` run on it, and the reference's metric formulas, written out here as its
utils/metrix_ds.py computes them, give the report's numbers."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from test_import import example, serialize_tensor, write_tfrecord

from xvoe.cli import main
from xvoe.scenes import store
from xvoe.scenes.released import _TEST_FILES

FRAMES, SIZE, SLOTS, PAIRS = 15, 128, 8, 2
UNEVEN = {"collision": (3, 1, 2, 2, 2, 2)}     # records per file: blocks of 2 across file boundaries


def scene(rng: np.random.Generator, impossible: bool) -> tuple[np.ndarray, np.ndarray]:
    """(raw_image (T, 128, 128, 4), amodal masks (T, 8, 128, 128, 1)): a ball rolls behind a
    wall (slot 7, near) past a small cube; the impossible member's ball comes out where it went in."""
    image = np.zeros((FRAMES, SIZE, SIZE, 4), np.uint8)
    masks = np.zeros((FRAMES, SLOTS, SIZE, SIZE, 1), np.uint8)
    image[..., :3] = rng.integers(0, 256, 3)
    image[..., 3] = 250
    rows, cols = np.mgrid[:SIZE, :SIZE]
    start, speed = rng.uniform(10, 30), rng.uniform(5, 7)
    for t in range(FRAMES):
        x = start + speed * t if not (impossible and t > FRAMES // 2) else start + speed * (FRAMES - t)
        ball = (rows - 96) ** 2 + (cols - x) ** 2 < 81
        cube = (rows >= 104) & (rows < 107) & (cols >= 100) & (cols < 103)     # smaller than a 4x4 block
        wall = (rows >= 40) & (rows < 110) & (cols >= 50) & (cols < 78) if 2 < t < FRAMES - 2 else rows < 0
        for slot, (where, colour, depth) in enumerate([(ball, (200, 30, 30), 120), (cube, (30, 200, 30), 130)]):
            image[t][where] = (*colour, depth)
            masks[t, slot, where, 0] = 1            # amodal: the part behind the wall too
        image[t][wall] = (90, 90, 200, 60)
        masks[t, 7, wall, 0] = 1
    return image, masks


def write_release(root: Path, seed: int = 0) -> None:
    """test/SCENARIO/eval-part-NNN.tfrecord as the reference's files lay out blocks: setting by
    setting, member 0 then member 1, PAIRS records each; collision's cut unevenly into files."""
    rng = np.random.default_rng(seed)
    for scenario, files in _TEST_FILES.items():
        videos = [scene(rng, impossible=block in (1, 5)) for block in range(files) for _ in range(PAIRS)]
        records = [example({"raw_image": serialize_tensor(image), "mask": serialize_tensor(masks)})
                   for image, masks in videos]
        counts = UNEVEN.get(scenario, (PAIRS,) * files)
        starts = np.cumsum((0, *counts))
        for part in range(files):
            write_tfrecord(root / "test" / scenario / f"eval-part-{part:03d}.tfrecord",
                           records[starts[part]:starts[part + 1]])


def count(difference: np.ndarray) -> np.ndarray:
    """The reference's `count`: 1 where the first is below the second, a half on a tie."""
    return (difference < 0) + 0.5 * (difference == 0)


def reference_metrics(blocks: list[np.ndarray]) -> dict[str, float]:
    """utils/metrix_ds.py's holistic, comparative and relative over a scenario's blocks of scores
    (block b: setting b // 2, member b % 2, by pair), as percent."""
    impossible = np.concatenate([blocks[1]] + ([blocks[5]] if len(blocks) == 6 else []))
    possible = np.concatenate([blocks[b] for b in (0, 2, 3, 4) if b < len(blocks)])
    found = {"holistic": count(possible[:, None] - impossible[None, :]).mean()}
    for setting in range(len(blocks) // 2):
        found[f"S{setting + 1}"] = count(blocks[2 * setting] - blocks[2 * setting + 1]).mean()
    s1 = (blocks[0] + blocks[1]) * 0.5
    names = ("S2-ext1", "S2-ext2", "S3-ext", "S3-sur")
    for block, name in zip(range(2, len(blocks)), names):
        found[name] = count((blocks[block] - s1) * (-1.0 if name == "S3-sur" else 1.0)).mean()
    return {name: 100.0 * value for name, value in found.items()}


def test_the_release_imports_at_32_and_the_shipped_model_scores_it(tmp_path, capsys):
    write_release(tmp_path / "X-VoE")
    data = tmp_path / "released-32.h5"
    assert main(["import", str(tmp_path / "X-VoE"), "--split", "test", "--size", "32", "--out", str(data),
                 "--quiet"]) == 0
    warned = capsys.readouterr().err.strip().splitlines()
    assert len(warned) == 2, warned
    assert "collision's files hold 3, 1, 2, 2, 2, 2 records, not one block of 2" in warned[0]
    assert "under more than one slot's mask" in warned[1] and int(warned[1].split()[3]) > 0
    with store.open_dataset(data, "test") as file:
        assert file["rgbd"].shape[1:] == (FRAMES, 32, 32, 4)
        assert (file["ids"][:] == 2).any(axis=(2, 3)).all()        # the 3x3 cube is in every frame at 32x32
        assert json.loads(file.attrs["config"])["source_size"] == SIZE

    scores = tmp_path / "xpl.csv"
    assert main(["score", "--model", "xpl", "--data", str(data), "--out", str(scores), "--quiet"]) == 0
    report = tmp_path / "report"
    assert main(["metrics", str(scores), "--out", str(report), "--rounds", "20", "--table", "md"]) == 0
    capsys.readouterr()

    with open(scores, newline="") as handle:
        rows = list(csv.DictReader(handle))
    with open(report / "metrics.csv", newline="") as handle:
        measured = {(r["metric"], r["scenario"], r["setting"]): 100.0 * float(r["value"])
                    for r in csv.DictReader(handle) if r["column"] == "score"}
    table = (report / "table.md").read_text()
    for scenario, files in _TEST_FILES.items():
        ours = [r for r in rows if r["scenario"] == scenario]
        blocks = [np.array([float(r["score"]) for r in sorted(ours, key=lambda r: int(r["pair"]))
                            if r["setting"] == f"S{b // 2 + 1}" and int(r["member"]) == b % 2])
                  for b in range(files)]
        official = reference_metrics(blocks)
        assert official["holistic"] == pytest.approx(measured["holistic", scenario, ""])
        for setting in ("S1", "S2", "S3")[:files // 2]:
            assert official[setting] == pytest.approx(measured["comparative", scenario, setting])
        assert (official["S2-ext1"] + official["S2-ext2"]) / 2 == pytest.approx(measured["relative", scenario, "S2"])
        if files == 6:
            assert (official["S3-ext"] + official["S3-sur"]) / 2 == \
                pytest.approx(measured["relative", scenario, "S3"])
        column = list(_TEST_FILES).index(scenario) + 4       # | metric | setting | model | collision | ...
        for name in ("S2-ext1", "S2-ext2", "S3-ext", "S3-sur")[:files - 2]:
            line = next(line for line in table.splitlines() if f"| {name} |" in line)
            assert line.split("|")[column].strip() == f"{official[name]:.1f}"
