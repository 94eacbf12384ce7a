"""Bad input never crashes or lies: every verb, fed a malformed input, exits with code 2 and
one line on stderr naming the problem, and writes or changes nothing."""
from __future__ import annotations

import contextlib
import csv
import gzip
import hashlib
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import typing
from dataclasses import fields
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given
from hypothesis import settings as hypothesis_settings
from hypothesis import strategies as st

from xvoe.cli import main
from xvoe.errors import XvoeError
from xvoe.evaluation.score_tables import read_scores, score_problem
from xvoe.models.config import _domain_of, field_type, override, parse_field
from xvoe.models.dynamics import DynamicsConfig
from xvoe.models.nll import InferenceConfig
from xvoe.models.perception import PerceptionConfig
from xvoe.models.phydnet import PhyDNetConfig
from xvoe.models.reasoning import ReasoningConfig
from xvoe.models.xpl import XPLConfig
from xvoe.outputs import atomic_paths, remove_stale_temporaries
from xvoe.scenes import store
from xvoe.scenes.generate import GenerateConfig, generate
from xvoe.training.checkpoints import shipped_path
from xvoe.training.config import TrainConfig
from xvoe.training.latents import _Latents, _write_latents
from xvoe.training.xpl import fingerprint

EXAMPLES = Path(__file__).resolve().parent.parent / "xvoe" / "examples"


def snapshot(root: Path) -> dict[str, str]:
    """Every file and folder under root (hidden ones too), a file with its hash."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
            for p in sorted(root.rglob("*"))}


def run(args: list[str], capsys) -> tuple[int, str]:
    """`xvoe ARGS` in this process: its exit code and stderr. Any exception other than the
    parser's exit is a traceback a user would see, and fails the test."""
    try:
        code = main(args)
    except SystemExit as stop:
        code = stop.code
    return code, capsys.readouterr().err


def mutate(source: Path, target: Path, change) -> Path:
    shutil.copy(source, target)
    with h5py.File(target, "r+") as file:
        change(file)
    return target


def _replace(file, name, data):
    del file[name]
    file.create_dataset(name, data=data)


MALFORMED = {
    "no-rgbd": lambda f: f.__delitem__("rgbd"),
    "no-states": lambda f: f.__delitem__("states"),
    "no-scenario": lambda f: f.__delitem__("scenario"),
    "no-split": lambda f: f.attrs.__delitem__("split"),
    "rgb-only": lambda f: _replace(f, "rgbd", f["rgbd"][..., :3]),
    "integer-scenario": lambda f: _replace(f, "scenario", np.zeros(f["scenario"].shape[0], np.int64)),
    "fewer-videos": lambda f: _replace(f, "rgbd", f["rgbd"][:10]),
    "int16-rgbd": lambda f: _replace(f, "rgbd", np.linspace(-500, 9700, f["rgbd"].size).astype(np.int16)
                                     .reshape(f["rgbd"].shape)),
    "all-collision": lambda f: _replace(f, "scenario", np.array(["collision"] * len(f["scenario"]), object)),
    "telekinesis": lambda f: _replace(f, "scenario", np.array(["telekinesis"] * len(f["scenario"]), object)),
    "event-past-end": lambda f: f["event_frame"].__setitem__(0, f["rgbd"].shape[1] + 4),
    "possible-swapped": lambda f: _replace(f, "possible", ~f["possible"][:]),
    "lonely-member": lambda f: f["pair"].__setitem__(1, 999),
    "ids-past-slots": lambda f: f["ids"].__setitem__((0, 0, 0, 0), 200),
    "kind-past-names": lambda f: f["kind"].__setitem__((0, 0), 99),
    "config-not-json": lambda f: f.attrs.__setitem__("config", "{size: 32"),
}


# training splits whose labels disagree with a training split's layout: (change, what the error says)
MALFORMED_TRAIN = {
    "unknown-group": (lambda f: _replace(f, "group", np.array(["juggling"] * len(f["group"]), object)),
                      "group 'juggling'"),
    "train-event-past-end": (lambda f: f["event_frame"].__setitem__(3, 99), "event_frame 99"),
}


def zero_chunk(path: Path, name: str, video: int) -> Path:
    """Damage `path` on disk as a bad sector would: the stored (compressed) chunk of `video`'s
    `name` overwritten with zeros."""
    with h5py.File(path, "r") as file:
        chunk = file[name].id.get_chunk_info(video)      # one video per chunk: chunk i is video i
    with open(path, "r+b") as handle:
        handle.seek(chunk.byte_offset)
        handle.write(bytes(chunk.size))
    return path


def damaged_splits(root: Path) -> dict[str, Path]:
    """Splits at the shipped models' frame size (32), whole and with video 1's frames damaged on
    disk, and two shards to merge, the second with video 1's ids damaged."""
    made = {}
    for split, size in (("test", dict(pairs=2)), ("train", dict(videos=4))):
        path = generate(GenerateConfig(split, size=32, seed=6, **size), root / f"damaged-{split}.h5", progress=False)
        made[f"{split}-32"] = shutil.copy(path, root / f"{split}-32.h5")
        made[f"damaged-{split}"] = zero_chunk(path, "rgbd", 1)
    for shard in (0, 1):
        made[f"shard-{shard}"] = generate(GenerateConfig("test", pairs=2, size=16, seed=6), root / f"shard-{shard}.h5",
                                          shard=(shard, 2), progress=False)
    zero_chunk(made["shard-1"], "ids", 1)
    return made


@pytest.fixture(scope="module")
def files(test_file, train_file, tmp_path_factory):
    """The malformed splits, made once, in a folder of their own."""
    root = tmp_path_factory.mktemp("malformed")
    made = {name: mutate(test_file, root / f"{name}.h5", change) for name, change in MALFORMED.items()}
    made |= {name: mutate(train_file, root / f"{name}.h5", change) for name, (change, _) in MALFORMED_TRAIN.items()}
    # the test split's layout and labels from another seed (small frames, for speed)
    other = generate(GenerateConfig("test", pairs=8, size=16, seed=4), root / "other.h5", progress=False)
    return made | damaged_splits(root) | {"test": test_file, "train": train_file, "other": other}


def case_lines(files, tmp: Path) -> list[tuple[list[str], str]]:
    """(arguments, what the error must say) for every verb and bad input."""
    cases = []
    for name in MALFORMED:
        bad = str(files[name])
        cases += [
            (["show", bad, "--out", str(tmp / "s.png")], bad),
            (["list", bad], bad),
            (["score", "--model", "random", "--data", bad, "--out", str(tmp / "s.csv")], bad),
            (["explain", "--model", "xpl", "--data", bad, "--out", str(tmp / "e.png")], bad),
            (["train", "perception", "--data", bad, "--out", str(tmp / "run"), "--steps", "1", "--quiet"], bad),
            (["encode", "--model", "xpl", "--data", bad, "--out", str(tmp / "run"), "--quiet"], bad),
        ]
    for name, (_, needle) in MALFORMED_TRAIN.items():
        cases += [
            (["train", "perception", "--data", str(files[name]), "--out", str(tmp / "run"), "--quiet"], needle),
            (["train", "xpl", "--data", str(files[name]), "--out", str(tmp / "run"), "--quiet"], needle),
        ]
    test, train = str(files["test"]), str(files["train"])
    a_file = tmp / "a-file"
    a_file.write_text("not a directory")
    (tmp / "taken.csv").write_text("earlier scores")
    (tmp / "taken.curves.npz").write_text("earlier curves")
    (tmp / "taken.png").write_text("earlier picture")
    (tmp / "report").mkdir()
    (tmp / "report" / "metrics.csv").write_text("earlier report")
    (tmp / "constant.py").write_text("import numpy as np\nclass Constant:\n    name = 'constant'\n"
                                     "    def surprise(self, videos):\n"
                                     "        return np.ones((len(videos.rgbd), videos.frames))\n")
    (tmp / "corrupt").mkdir()
    for stage in ("perception", "xpl"):
        (tmp / "corrupt" / f"{stage}.pt").write_bytes(b"not a checkpoint")
    cases += [
        (["generate", "--split", "test", "--pairs", "1", "--out", str(tmp), "--overwrite", "--quiet"],
         "is a directory"),
        (["generate", "--split", "test", "--pairs", "1", "--out", "", "--quiet"], "--out is empty"),
        (["generate", "--split", "test", "--merge", test, "--out", str(tmp / "m.h5")], "leave out --split"),
        (["generate", "--split", "test", "--shard", "-1/2", "--out", str(tmp / "g.h5")], "0 <= I < N"),
        (["show", str(tmp), "--out", str(tmp / "s.png")], "is a directory"),
        (["show", test, "--out", str(tmp / "taken.png")], "--overwrite"),
        (["show", test, "--index", "5000", "--out", str(tmp / "s.png")], "out of range"),
        (["list", test, "--scenario", "telekinesis"], "holds no scenario 'telekinesis'; it holds collision"),
        (["list", test, "--scenario", "permanence", "--setting", "S3"], "it holds S1, S2"),
        (["list", test, "--setting", "2"], "holds no setting '2'"),
        (["list", test, "--member", "2"], "it holds 0 and 1"),
        (["list", test, "--pair", "99"], "holds no pair 99"),
        (["list", test, "--pair", "first"], "pair: expected"),
        (["list", train], "pairs live in test splits"),
        (["list", str(tmp / "nowhere.h5")], "no such file"),
        (["explain", "--model", "xpl", "--data", test, "--out", str(tmp / "taken.png")], "--overwrite"),
        (["score", "--model", "random", "--data", test, "--out", str(tmp / "taken.csv")], "--overwrite"),
        (["score", "--model", "random", "--data", train, "--out", str(tmp / "s.csv")], "test split"),
        (["score", "--model", f"{tmp / 'constant.py'}:Constant", "--data", test, "--out", str(tmp / "s.csv"),
          "--quiet"], "failed the check 'spread'"),
        (["score", "--model", "random", "--data", test, "--out", str(tmp / "taken.png").replace(".png", ".csv")
          .replace("taken", "fresh"), "--aggregate", "mean"], "invalid choice"),
        (["score", "--model", "xpl", "--data", test, "--out", str(tmp / "n.csv"), "--surprise", "nll",
          "--nll-set", "nonsense=1"], "no field 'nonsense'"),
        (["score", "--model", "xpl", "--data", test, "--out", str(tmp / "n.csv"), "--surprise", "nll",
          "--nll-set", "pixel_sigma=wide"], "a number"),
        (["score", "--model", "xpl", "--data", test, "--out", str(tmp / "n.csv"), "--surprise", "nll",
          "--particles", "16", "--nll-set", "particles=8"], "give the particles once"),
        (["score", "--model", "xpl", "--data", test, "--out", str(tmp / "e.csv"), "--explanation", "better"],
         "unrecognized arguments"),
        (["explain", "--model", "xpl", "--data", test, "--out", str(tmp / "e.png"), "--explanation", "best"],
         "invalid choice"),
        (["metrics", str(tmp / "nowhere.csv"), "--out", str(tmp / "r")], "no such file"),
        (["train", "perception", "--data", test, "--out", str(tmp / "run"), "--quiet"], "training on impossible"),
        (["train", "phydnet", "--data", test, "--out", str(tmp / "run"), "--quiet"], "training on impossible"),
        (["train", "perception", "--data", train, "--out", str(a_file), "--steps", "1", "--quiet"], "is a file"),
        (["train", "xpl", "--data", train, "--out", str(tmp / "run"), "--set", "nonsense=1"], "no field"),
        (["train", "xpl", "--data", train, "--out", str(tmp / "run"), "--set", "steps=many"], "whole number"),
        (["pipeline", "--out", str(tmp / "p"), "--models", ""], "names no model"),
        (["pipeline", "--out", str(tmp / "p"), "--train-processes", "-1"], "--train-processes must be"),
        (["pipeline", "--out", str(a_file), "--models", "random", "--train-videos", "2", "--pairs", "1"],
         "is a file"),
        # a device this machine lacks (no machine has a hundredth GPU), or none at all
        (["score", "--model", "xpl", "--data", test, "--out", str(tmp / "d.csv"), "--device", "cuda:99"], "'cuda:99'"),
        (["explain", "--model", "xpl", "--data", test, "--out", str(tmp / "d.png"), "--device", "cuda:99"],
         "'cuda:99'"),
        (["train", "perception", "--data", train, "--out", str(tmp / "run"), "--device", "tpu"], "is not a device"),
        (["pipeline", "--out", str(tmp / "p"), "--device", "cuda:99"], "'cuda:99'"),
        (["ship", str(tmp / "corrupt"), "--out", str(tmp / "weights")], "not a readable xvoe checkpoint"),
        (["ship", str(tmp / "nowhere"), "--out", str(tmp / "weights")], "no such run directory"),
    ]
    return (cases + domain_cases(files, tmp) + path_cases(files, tmp) + kind_cases(files, tmp) + split_cases(files, tmp)
            + damage_cases(files, tmp) + checkpoint_cases(files, tmp) + own_model_cases(files, tmp)
            + edited_score_cases(files, tmp) + video_value_cases(files, tmp))


def edited_checkpoint(run: Path, stage: str, change, shipped: str = "xpl") -> Path:
    """RUN/STAGE.pt: the shipped model's checkpoint of `stage` with `change` made to its contents,
    beside the shipped perception."""
    run.mkdir(exist_ok=True)
    if not (run / "perception.pt").exists():
        shutil.copy(shipped_path(shipped, "perception"), run / "perception.pt")
    state = torch.load(shipped_path(shipped, stage), weights_only=True)
    change(state)
    torch.save(state, run / f"{stage}.pt")
    return run / f"{stage}.pt"


def _first(weights: dict) -> str:
    return next(iter(weights))


def checkpoint_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Checkpoints that are not what they claim: each named by file and key on loading, by
    every verb (a resumed run too)."""
    weights = torch.load(shipped_path("xpl"), weights_only=True)["model"]
    first, shape = _first(weights), tuple(weights[_first(weights)].shape)
    edits = {
        "no-model": ("xpl", lambda s: s.pop("model"), "it has no model key"),
        "missing-tensor": ("xpl", lambda s: s["model"].pop(first), f"model lacks {first}"),
        "misshaped": ("xpl", lambda s: s["model"].__setitem__(first, torch.zeros(3, 5)),
                      f"{first} has shape (3, 5), the model {shape}"),
        "config-type": ("xpl", lambda s: s["config"]["xpl"].__setitem__("stop_target_gradient", "yes"),
                        "config.xpl.stop_target_gradient is 'yes', not a bool"),
        "config-list": ("xpl", lambda s: s.__setitem__("config", [1, 2]), "config is a list, not a dict"),
        "step-text": ("xpl", lambda s: s.__setitem__("step", "12"), "step is '12', not a whole number"),
        "nan-perception": ("perception", lambda s: [t.fill_(float("nan")) for t in s["model"].values()
                                                    if t.is_floating_point()], "holds weights that are not finite"),
        "perception-misshaped": ("perception", lambda s: s["model"].__setitem__(_first(s["model"]), torch.zeros(2)),
                                 "has shape (2,), the model"),
        "phydnet-misshaped": ("phydnet", lambda s: s["model"].__setitem__(_first(s["model"]), torch.zeros(2)),
                              "has shape (2,), the model"),
    }
    made = {name: edited_checkpoint(tmp / name, stage, change, "phydnet" if stage == "phydnet" else "xpl")
            for name, (stage, change, _) in edits.items()}
    # a proposal.pt (part of the network, loaded over xpl.pt) whose tensor fits nowhere
    proposal = tmp / "proposal-misshaped"
    edited_checkpoint(proposal, "xpl", lambda s: None)
    fingerprint_of = torch.load(proposal / "xpl.pt", weights_only=True)
    tuned = {"format": 1, "stage": "proposal", "config": fingerprint_of["config"], "step": 1,
             "meta": {"xpl_fingerprint": fingerprint(fingerprint_of["model"])},
             "model": {"transformer2.nothing.weight": torch.zeros(2)}}
    torch.save(tuned, proposal / "proposal.pt")
    test = str(files["test-32"])
    cases = []
    for name, (stage, _, needle) in edits.items():
        model = str(made[name]) if stage == "phydnet" else str(made[name].parent)
        cases.append((["score", "--model", model, "--data", test, "--out", str(tmp / "c.csv"), "--quiet"],
                      f"{made[name]} {needle}" if needle.startswith("holds") else needle))
        if name in ("no-model", "config-type", "config-list", "step-text"):    # refused before the data is asked for
            cases.append((["train", "xpl", "--out", str(made[name].parent), "--resume", "--steps", "1", "--quiet"],
                          f"{made[name]} does not fit the xpl model: {needle}"))
    # a resumed run whose weights do not fit the network it builds
    perception = made["perception-misshaped"]
    cases.append((["train", "perception", "--data", str(files["train-32"]), "--out", str(perception.parent), "--resume",
                   "--steps", "1", "--set", "airborne_share=0", "--quiet"],
                  f"{perception} does not fit the perception model"))
    cases.append((["train", "xpl", "--out", str(made["misshaped"].parent), "--resume", "--steps", "1", "--quiet"],
                  f"{made['misshaped']} records no latents to resume on"))
    cases.append((["explain", "--model", str(made["misshaped"].parent), "--data", test, "--out", str(tmp / "c.png")],
                  f"{made['misshaped']} does not fit the xpl model: {first} has shape (3, 5)"))
    cases.append((["score", "--model", str(proposal), "--data", test, "--out", str(tmp / "c.csv"), "--quiet"],
                  f"{proposal / 'proposal.pt'} does not fit the proposal model: model holds transformer2.nothing"))
    return cases


def damage_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """A split whose video 1 is damaged on disk, at every verb that reads its frames (and the
    merge that copies them): named by file and video wherever it is read."""
    test, train = str(files["damaged-test"]), str(files["damaged-train"])
    named = f"{test} is damaged: video 1's rgbd cannot be read"
    return [
        (["show", test, "--index", "1", "--out", str(tmp / "s.png")], named),
        (["score", "--model", "random", "--data", test, "--out", str(tmp / "s.csv"), "--quiet"], named),
        (["explain", "--model", "xpl", "--data", test, "--index", "1", "--out", str(tmp / "e.png")], named),
        (["train", "perception", "--data", train, "--out", str(tmp / "run"), "--steps", "1", "--quiet"],
         f"{train} is damaged: video 1's rgbd"),
        (["train", "phydnet", "--data", train, "--out", str(tmp / "run"), "--steps", "1", "--quiet"],
         f"{train} is damaged: video 1's rgbd"),
        (["encode", "--model", "xpl", "--data", train, "--out", str(tmp / "new-run"), "--quiet"],
         f"{train} is damaged: video 1's rgbd"),
        (["generate", "--merge", str(files["shard-0"]), str(files["shard-1"]), "--out", str(tmp / "m.h5"), "--quiet"],
         f"{files['shard-1']} is damaged: video 1's ids cannot be read"),
    ]


OWN_MODELS = """
import sys
import time

import numpy as np


def ones(videos):
    return np.stack([np.random.default_rng(int(i)).random(videos.frames) for i in videos.index])


class InitRaises:
    name = "init-raises"
    def __init__(self):
        raise ValueError("no weights here")
    def surprise(self, videos):
        return ones(videos)


class Raises:
    name = "raises"
    def surprise(self, videos):
        raise RuntimeError("lost\\nits way")


class Text:
    name = "text"
    def surprise(self, videos):
        return [["high"] * videos.frames for _ in videos.index]


class Ragged:
    name = "ragged"
    def surprise(self, videos):
        return [list(ones(videos)[i][:videos.frames - (i == 1)]) for i in range(len(videos.index))]


class Complex:
    name = "complex"
    def surprise(self, videos):
        return ones(videos) * (1 + 1j)


class Infinite:
    name = "infinite"
    def surprise(self, videos):
        found = ones(videos)
        found[videos.index == 5] = np.inf
        return found


class Exits:
    name = "exits"
    def surprise(self, videos):
        sys.exit(3)


class Hangs:
    name = "hangs"
    def surprise(self, videos):
        while True:
            try:
                time.sleep(60)
            except Exception:
                pass


class Newline:
    name = "two\\nlines"
    def surprise(self, videos):
        return ones(videos)


class Nameless:
    name = ""
    def surprise(self, videos):
        return ones(videos)


class ExplainRaises:
    name = "explain-raises"
    def surprise(self, videos):
        return ones(videos)
    def explain(self, videos):
        raise KeyError("nothing behind")
"""


def own_model_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Models of one's own that misbehave: each ends in one line naming the model and what it did."""
    (tmp / "own.py").write_text(OWN_MODELS)
    (tmp / "exits_at_import.py").write_text("import sys\nsys.exit(3)\n")
    score = ["score", "--data", str(files["test"]), "--out", str(tmp / "own.csv"), "--quiet", "--model"]
    own = str(tmp / "own.py")
    return [
        (score + [f"{own}:InitRaises"], "InitRaises() raised ValueError: no weights here"),
        (score + [f"{own}:Raises"], "the model raises failed on videos"),
        (score + [f"{own}:Raises"], "surprise raised RuntimeError: lost its way"),
        (score + [f"{own}:Text"], "the model text gave values of type <U4 (not numbers) for video"),
        (score + [f"{own}:Ragged"], "the model ragged gave a row of shape (14,), not (15,) for video"),
        (score + [f"{own}:Complex"], "the model complex gave complex numbers for video"),
        (score + [f"{own}:Infinite", "--no-checks"], "NaN or infinite for video 5"),
        (score + [f"{own}:Exits"], "surprise raised SystemExit: 3"),
        (score + [f"{tmp / 'exits_at_import.py'}:Model"], "SystemExit: 3"),
        (score + [f"{own}:Hangs", "--time-limit", "0.3"], "the model hangs gave no surprise for videos"),
        (score + [f"{own}:Newline"], "name holds a control character"),
        (score + [f"{own}:Nameless"], "name is empty"),
        (score + ["random", "--time-limit", "0"], "--time-limit"),
        (["explain", "--model", f"{own}:ExplainRaises", "--data", str(files["test"]), "--index", "3", "--out",
          str(tmp / "own.png")], "the model explain-raises failed on video 3: explain raised KeyError"),
    ]


def _rewrite_rows(source: Path, target: Path, change) -> Path:
    """A copy of a score file (its curves beside it) with its rows changed by hand."""
    with open(source, newline="") as handle:
        rows = list(csv.reader(handle))
    change(rows)
    with open(target, "w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    shutil.copy(source.with_suffix(".curves.npz"), target.with_suffix(".curves.npz"))
    return target


def edited_score_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Score files edited by hand, and curves that are not their score file's."""
    test = str(files["test"])
    ours = tmp / "edited-source.csv"
    main(["score", "--model", "random", "--data", test, "--out", str(ours), "--quiet"])
    mine = tmp / "mine.csv"
    main(["score", "--model", f"{EXAMPLES / 'frame_change.py'}:FrameChange", "--data", test, "--out", str(mine),
          "--quiet"])
    extra = _rewrite_rows(ours, tmp / "extra.csv", lambda rows: rows[3].append("7"))
    two = _rewrite_rows(ours, tmp / "two.csv", lambda rows: rows[4].__setitem__(1, "other"))
    nameless = _rewrite_rows(ours, tmp / "nameless.csv", lambda rows: [row.__setitem__(1, "") for row in rows[1:]])
    edited = _rewrite_rows(ours, tmp / "edited.csv", lambda rows: rows[9].__setitem__(7, "0.5"))
    swapped = tmp / "swapped.csv"
    shutil.copy(ours, swapped)
    shutil.copy(mine.with_suffix(".curves.npz"), swapped.with_suffix(".curves.npz"))
    report = ["--out", str(tmp / "r"), "--rounds", "5"]
    return [
        (["metrics", str(extra)] + report, "row 3 (line 4) has more fields than the header"),
        (["metrics", str(two)] + report, "two models, 'random' and 'other' (row 4)"),
        (["metrics", str(nameless)] + report, "row 1's model name is empty"),
        (["metrics", str(swapped)] + report, "was written with other scores than"),
        (["metrics", str(edited)] + report, "was written with other scores than"),
        (["show", test, "--out", str(tmp / "s.mp4"), "--scores", str(swapped)], "was written with other scores than"),
    ]


def video_value_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Slot ids and states checked in every video where read, not only the first and last."""
    source = files["test-32"]
    ids = mutate(source, tmp / "ids-middle.h5", lambda f: f["ids"].__setitem__((5, 3, 0, 0), 200))
    nan = mutate(source, tmp / "nan-states.h5", lambda f: f["states"].__setitem__((5, 3, 0, 0), np.nan))
    inf = mutate(source, tmp / "inf-states.h5", lambda f: f["states"].__setitem__((5, 3, 0, 1), np.inf))
    named = f"{ids} has slot ids up to 200 in video 5"
    return [
        (["score", "--model", "random", "--data", str(ids), "--out", str(tmp / "v.csv"), "--quiet"], named),
        (["show", str(ids), "--index", "5", "--out", str(tmp / "v.png")], named),
        (["explain", "--model", "xpl", "--data", str(ids), "--index", "5", "--out", str(tmp / "v.png")], named),
        (["show", str(nan), "--index", "5", "--out", str(tmp / "v.png")],
         f"{nan} has NaN or infinite states in video 5"),
        (["explain", "--model", "xpl", "--data", str(inf), "--index", "5", "--out", str(tmp / "v.png")],
         f"{inf} has NaN or infinite states in video 5"),
    ]


HUGE = str(2**70)


def domain_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Settings outside their domain, as flags, --set and --nll-set; and refused before a split is encoded."""
    test, train = str(files["test"]), str(files["train"])
    xpl = ["train", "xpl", "--data", train, "--out", str(tmp / "run"), "--quiet"]
    nll = ["score", "--model", "xpl", "--data", test, "--out", str(tmp / "n.csv"), "--surprise", "nll"]
    return [
        (xpl + ["--lr", "nan"], "lr must be"),
        (xpl + ["--lr", "-1"], "lr must be"),
        (xpl + ["--set", "lr=inf"], "lr must be"),
        (xpl + ["--set", "warmup_steps=-3"], "warmup_steps must be"),
        (xpl + ["--set", "model.dynamics.hidden=0"], "dynamics.hidden must be"),
        (xpl + ["--set", "model.mae_weight=nan"], "mae_weight must be"),
        (xpl + ["--seed", HUGE], "seed must be"),
        (xpl + ["--steps", "1.5"], "steps: expected a whole number"),
        (["train", "perception", "--data", train, "--out", str(tmp / "run"), "--minutes", "nan"], "minutes must be"),
        (["train", "perception", "--data", train, "--out", str(tmp / "run"), "--set", "sigma=-0.1"], "sigma must be"),
        (["train", "phydnet", "--data", train, "--out", str(tmp / "run"), "--set", "change_weight=-1"],
         "change_weight must be"),
        (["generate", "--split", "test", "--seed", HUGE, "--out", str(tmp / "g.h5")], "seed must be"),
        (["generate", "--split", "test", "--seed", "-1", "--out", str(tmp / "g.h5")], "seed must be"),
        (["generate", "--split", "test", "--frames", "3", "--out", str(tmp / "g.h5")], "frames must be"),
        (["score", "--model", "random", "--data", test, "--out", str(tmp / "s.csv"), "--seed", HUGE], "seed must be"),
        (nll + ["--nll-set", "pixel_sigma=-1"], "pixel_sigma must be"),
        (nll + ["--nll-set", "prior_hidden=nan"], "prior_hidden must be"),
        (nll + ["--nll-set", "smc_proposal_widening=3,-inf"], "smc_proposal_widening must be"),
        (nll + ["--particles", "0"], "particles must be"),
        (["explain", "--model", "xpl", "--data", test, "--out", str(tmp / "e.png"), "--index", "-1"], "index must be"),
        (["explain", "--model", "xpl", "--data", test, "--out", str(tmp / "e.png"), "--display-size", "8"],
         "display-size must be"),
        (["show", test, "--out", str(tmp / "s.png"), "--display-size", "1000"], "display-size must be"),
        (["show", test, "--out", str(tmp / "s.gif"), "--display-size", "big"], "display-size: expected"),
        (["metrics", str(tmp / "taken.csv"), "--out", str(tmp / "r"), "--seed", "-5"], "seed must be"),
        (xpl + ["--focus-share", "2"], "focus_share must be"),
        (xpl + ["--focus-share", "-0.5"], "focus_share must be"),
        (xpl + ["--focus-share", "nan"], "focus_share must be"),
        (xpl + ["--focus-group", "juggling", "--focus-share", "0.5"], "names no group 'juggling'"),
        (xpl + ["--set", "focus_group=permanence,juggling"], "names no group 'juggling'"),
        (xpl + ["--perception", "xpl", "--focus-share", "0.5"], "focus_share needs a focus_group"),
        (xpl + ["--perception", "xpl", "--set", "focus_share=0.3"], "focus_share needs a focus_group"),
    ]


def path_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Outputs that are an input of the same command (by any name), or of a suffix not written."""
    data, train = tmp / "input.h5", tmp / "train-input.h5"
    shutil.copy(files["test"], data)
    shutil.copy(files["train"], train)
    (tmp / "link.csv").symlink_to(data)
    (tmp / "alias.h5").symlink_to(data)
    (tmp / "cached").mkdir()        # where encode and show write when no output is named: links to the input
    (tmp / "cached" / "latents-train-input.h5").symlink_to(train)
    (tmp / "input.0.png").symlink_to(data)
    score = ["score", "--model", "random", "--data", str(data), "--overwrite"]
    return [
        (score + ["--out", str(data)], "is the input"),
        (score + ["--out", str(tmp / "link.csv")], "is the input"),
        (["score", "--model", "random", "--data", str(tmp / "alias.h5"), "--out", str(data), "--overwrite"],
         "is the input"),
        (score + ["--out", str(tmp / "s.h5")], "--out must end in .csv, not .h5"),
        (["generate", "--merge", str(data), "--out", str(tmp / "alias.h5"), "--overwrite"], "is the input"),
        (["generate", "--split", "test", "--out", str(tmp / "g.csv")], "--out must end in .h5, not .csv"),
        (["show", str(data), "--out", str(data), "--overwrite"], "is the input"),
        (["show", str(data), "--out", str(tmp / "s.bmp")], "--out must end in .png, .gif or .mp4"),
        (["explain", "--model", "xpl", "--data", str(data), "--out", str(tmp / "e.jpg")], "--out must end in .png"),
        (["encode", "--model", "xpl", "--data", str(data), "--out", str(tmp / "run"), "--cache", str(data),
          "--overwrite"], "--cache"),
        (["encode", "--model", "xpl", "--data", str(train), "--out", str(tmp / "cached"), "--overwrite"],
         "the default --cache"),
        (score + ["--out", str(tmp / "s.csv"), "--cache", str(tmp / "alias.h5")], "--cache"),
        (score + ["--out", str(tmp / "s.csv"), "--cache", str(tmp / "s.npz")], "--cache must end in .h5"),
        (["show", str(data), "--overwrite"], "the default --out"),
    ]


def kind_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """A checkpoint of one kind under the name of another."""
    swapped = tmp / "swapped"
    swapped.mkdir()
    shutil.copy(shipped_path("plato"), swapped / "xpl.pt")
    shutil.copy(shipped_path("xpl", "perception"), swapped / "perception.pt")
    shutil.copy(shipped_path("xpl"), swapped / "xpl-noresidual.pt")
    shutil.copy(shipped_path("xpl"), swapped / "phydnet.pt")
    shipping = tmp / "shipping"
    shipping.mkdir()
    shutil.copy(shipped_path("xpl", "perception"), shipping / "perception.pt")
    shutil.copy(shipped_path("xpl"), shipping / "plato.pt")
    score = ["score", "--data", str(files["test"]), "--out", str(tmp / "k.csv")]
    return [
        (score + ["--model", str(swapped)], "holds a plato model, not xpl"),
        (score + ["--model", str(swapped / "xpl-noresidual.pt")], "holds a xpl model, not xpl-noresidual"),
        (score + ["--model", str(swapped / "phydnet.pt")], "holds a xpl model, not phydnet"),
        (["explain", "--model", str(swapped / "xpl.pt"), "--data", str(files["test"]), "--out", str(tmp / "k.png")],
         "holds a plato model, not xpl"),
        (["train", "xpl", "--out", str(swapped), "--resume", "--steps", "1", "--quiet"],
         "holds a plato model, not xpl"),
        (["ship", str(shipping), "--out", str(tmp / "weights")], "holds a xpl model, not plato"),
    ]


def _rewrite_header(curves: Path, change) -> None:
    with np.load(curves) as saved:
        arrays = dict(saved)
    header = json.loads(str(arrays["header"]))
    change(header)
    np.savez_compressed(curves, **arrays | {"header": np.array(json.dumps(header))})


def split_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Scores of another split than the one named, or than each other; files verify cannot rescore."""
    test, other = str(files["test"]), str(files["other"])
    ours, theirs = tmp / "ours.csv", tmp / "theirs.csv"
    main(["score", "--model", "random", "--data", test, "--out", str(ours), "--quiet"])
    main(["score", "--model", str(EXAMPLES / "frame_change.py:FrameChange"), "--data", other, "--out", str(theirs),
          "--quiet"])
    old, foreign = tmp / "old.csv", tmp / "foreign.csv"
    for copy in (old, foreign):
        shutil.copy(ours, copy)
        shutil.copy(ours.with_suffix(".curves.npz"), copy.with_suffix(".curves.npz"))
    _rewrite_header(old.with_suffix(".curves.npz"), lambda h: (h.pop("split"), h.pop("model_identity")))
    _rewrite_header(foreign.with_suffix(".curves.npz"), lambda h: h["model_identity"].update(seed=1))
    return [
        (["metrics", str(ours), str(theirs), "--out", str(tmp / "r")], "scored on different splits"),
        (["metrics", str(theirs), "--data", test, "--out", str(tmp / "r")], "scored on another split"),
        (["show", test, "--out", str(tmp / "s.mp4"), "--scores", str(theirs)], "scored on another split"),
        (["verify", str(old)], "rescore it with this xvoe"),
        (["verify", str(foreign)], "was scored by another model than"),
        (["verify", str(tmp)], "holds no headers.json"),
        (["verify", str(ours), "--rows", "0"], "expected a number >= 1"),
    ]


def no_pixels(file: h5py.File) -> None:
    """Frames of 0x0 pixels, the split's shapes otherwise kept."""
    for name in ("rgbd", "ids"):
        shape = file[name].shape
        _replace(file, name, np.zeros((*shape[:2], 0, 0, *shape[4:]), np.uint8))


def declaring(source: Path, target: Path, videos: int) -> Path:
    """A copy of split `source` whose every dataset declares `videos` rows: its first video
    stored, the rest never written (HDF5 keeps unwritten chunks off the disk)."""
    shutil.copy(source, target)
    with h5py.File(target, "r+") as file:
        for name in [name for name in file if file[name].ndim]:
            first, attrs, dtype, shape = file[name][:1], dict(file[name].attrs), file[name].dtype, file[name].shape
            del file[name]
            chunks = (1, *shape[1:]) if len(shape) > 1 else (1 << 16,)
            grown = file.create_dataset(name, (videos, *shape[1:]), dtype, chunks=chunks, compression="gzip")
            grown[:1] = first
            grown.attrs.update(attrs)
    return target


def release_with(root: Path, record: bytes) -> Path:
    """A release (tests/test_import.py's writer) whose first collision file holds `record` alone."""
    from test_import import write_release

    write_release(root)
    with gzip.open(root / "test" / "collision" / "eval-part-000.tfrecord", "wb") as out:
        out.write(record)
    return root


def limit_cases(files, tmp: Path) -> list[tuple[list[str], str]]:
    """Names past the file system's limit, and sizes and counts past the machine's memory and
    cores: refused before any work."""
    from test_import import example, field, framed

    from xvoe.scenes.tfrecord import _masked_crc

    test, train = str(files["test-32"]), str(files["train-32"])
    long = "n" * 300
    zero = mutate(files["test-32"], tmp / "zero.h5", no_pixels)
    many = declaring(files["test-32"], tmp / "many.h5", 10**8)
    header = struct.pack("<Q", 2**62)
    huge_record = release_with(tmp / "huge-record", header + struct.pack("<I", _masked_crc(header)) + bytes(64))
    shape = b"".join(field(2, field(1, size)) for size in (10**6, 512, 512, 4))
    splat = field(1, 4) + field(2, shape) + field(7, 7)      # one value standing for all, as TensorFlow may write
    huge_tensor = release_with(tmp / "huge-tensor", framed(example({"raw_image": splat, "mask": splat, "slot": [0.0]})))
    beyond = str(len(os.sched_getaffinity(0)) + 1)
    nll = ["--model", "xpl", "--data", test, "--surprise", "nll", "--particles", str(10**9)]
    return [
        (["generate", "--split", "test", "--out", str(tmp / f"{long}.h5")], "holds a name of 303 bytes"),
        (["generate", "--split", "test", "--out", str(tmp / "g.h5") + "/"], "ends in a slash"),
        (["show", test, "--out", str(tmp / f"{long}.png")], "holds a name of 304 bytes"),
        (["show", str(tmp / f"{long}.h5"), "--out", str(tmp / "s.png")], "no such file"),
        (["score", "--model", "random", "--data", test, "--out", str(tmp / f"{long[:246]}.csv")],
         "the curves beside --out holds a name of 257 bytes"),
        (["metrics", str(tmp / "ours.csv"), "--out", str(tmp / long)], "holds a name of 300 bytes"),
        (["train", "perception", "--data", train, "--out", str(tmp / long), "--quiet"], "holds a name of 300 bytes"),
        (["encode", "--model", "xpl", "--data", train, "--out", str(tmp / long)], "holds a name of 300 bytes"),
        (["generate", "--split", "test", "--pairs", str(10**12), "--out", str(tmp / "g.h5")],
         "a split of 22,000,000,000,000 videos needs"),
        (["generate", "--split", "train", "--videos", str(10**15), "--out", str(tmp / "g.h5")],
         "a split of 1,000,000,000,000,000 videos needs"),
        (["generate", "--split", "test", "--workers", str(10**6), "--out", str(tmp / "g.h5")],
         f"--workers {10**6} is more than this machine's"),
        (["generate", "--split", "test", "--workers", beyond, "--out", str(tmp / "g.h5")],
         f"--workers {beyond} is more than this machine's"),
        (["score", "--model", "random", "--data", test, "--workers", beyond, "--out", str(tmp / "s.csv")],
         f"--workers {beyond} is more than this machine's"),
        (["train", "perception", "--data", train, "--out", str(tmp / "run"), "--batch-size", str(10**9),
          "--set", "airborne_share=0", "--quiet"],
         "--batch-size 1000000000 needs"),
        (["train", "phydnet", "--data", train, "--out", str(tmp / "run"), "--batch-size", str(10**9), "--quiet"],
         "--batch-size 1000000000 needs"),
        (["score", *nll, "--out", str(tmp / "n.csv")], "--particles 1,000,000,000 needs"),
        (["explain", *nll, "--out", str(tmp / "n.png")], "--particles 1,000,000,000 needs"),
        (["show", str(many), "--out", str(tmp / "s.png")], "declares 100,000,000 videos, whose states and labels need"),
        (["score", "--model", "random", "--data", str(many), "--out", str(tmp / "s.csv")], "declares 100,000,000"),
        (["show", str(zero), "--out", str(tmp / "s.png")], "frames of 0x0 pixels"),
        (["score", "--model", "random", "--data", str(zero), "--out", str(tmp / "s.csv")], "frames of 0x0 pixels"),
        (["import", str(huge_record), "--split", "test", "--out", str(tmp / "i.h5"), "--quiet"],
         "claims a record of 4,611,686,018,427,387,904 bytes"),
        (["import", str(huge_tensor), "--split", "test", "--out", str(tmp / "i.h5"), "--quiet"],
         "a tensor declares shape (1000000, 512, 512, 4)"),
    ]


def mounted_tmpfs(folder: Path, options: str) -> typing.Iterator[Path | None]:
    """A small tmpfs mounted at `folder` (made here) for the caller's block, or None where none
    can be mounted (not as root)."""
    folder.mkdir()
    mounted = os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                                                   capture_output=True).returncode == 0
    if not mounted:
        folder.rmdir()
    yield folder if mounted else None
    if mounted:
        subprocess.run(["umount", str(folder)], check=True)


@pytest.fixture
def full_disk(tmp_path):
    """A file system with no room left inside the test's folder (a small tmpfs, filled once the
    cases have put their files there), or None where none can be mounted (not as root)."""
    yield from mounted_tmpfs(tmp_path / "full", "size=1m")


def fill(folder: Path) -> None:
    """Write zeros into `folder` until its file system refuses another byte."""
    descriptor = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT)
    try:
        for size in (1 << 16, 1 << 12, 1):
            with contextlib.suppress(OSError):
                while True:
                    os.write(descriptor, bytes(size))
    finally:
        os.close(descriptor)


def full_disk_cases(files, full: Path | None) -> list[tuple[list[str], str]]:
    """Every verb that writes, on a file system with no room: one line naming the output, and
    nothing left (the old scores of --overwrite as they were)."""
    if full is None:
        return []
    test, train = str(files["test-32"]), str(files["train-32"])
    old = full / "old.csv"
    assert main(["score", "--model", "random", "--data", test, "--out", str(old), "--quiet"]) == 0
    fill(full)
    full_name = "no space left on device writing"
    return [
        (["generate", "--split", "test", "--pairs", "1", "--size", "32", "--out", str(full / "g.h5"), "--quiet"],
         f"a split of 22 videos needs at least 0.0769 MB of disk space, {full} has 0 MB free"),
        (["score", "--model", "random", "--data", test, "--out", str(full / "s.csv"), "--quiet"],
         f"{full_name} {full / 's.csv'}"),
        (["score", "--model", "random", "--data", test, "--out", str(old), "--seed", "1", "--overwrite", "--quiet"],
         f"{full_name} {old}"),
        (["train", "perception", "--data", train, "--out", str(full / "run"), "--steps", "1", "--set",
          "airborne_share=0", "--quiet"],
         f"{full_name} {full / 'run' / 'perception.pt'}"),
        (["metrics", str(old), "--rounds", "20", "--out", str(full / "r")], f"{full_name} {full / 'r'}"),
        (["show", test, "--out", str(full / "s.png")], f"{full_name} {full / 's.png'}"),
        (["show", test, "--out", str(full / "s.mp4")], f"{full_name} {full / 's.mp4'}"),
        (["encode", "--model", "xpl", "--data", train, "--out", str(full / "enc"), "--quiet"],
         f"{full_name} {full / 'enc' / 'latents-train-32.h5'}"),
    ]


def test_a_disk_that_fills_as_generate_writes_is_named_in_one_line(full_disk, capsys, monkeypatch):
    """generate refuses before the work a split that cannot fit; one that the estimate let
    through and that fills the disk all the same is named as every verb's is."""
    if full_disk is None:
        pytest.skip("mounts a file system: run as root")
    monkeypatch.setattr("xvoe.scenes.generate._least_bytes_per_video", lambda config: 0)
    fill(full_disk)
    before = snapshot(full_disk)
    code, err = run(["generate", "--split", "test", "--pairs", "1", "--size", "32", "--out", str(full_disk / "g.h5"),
                     "--quiet"], capsys)
    assert code == 2 and err == f"xvoe generate: error: no space left on device writing {full_disk / 'g.h5'}\n", err
    assert snapshot(full_disk) == before


@pytest.fixture
def read_only(tmp_path):
    """A file system mounted read-only inside the test's folder, or None where none can be
    mounted (not as root, who passes every permission check but this one)."""
    yield from mounted_tmpfs(tmp_path / "read-only", "ro,size=1m")


def read_only_cases(files, folder: Path | None) -> list[tuple[list[str], str]]:
    """Every verb that writes, into a read-only file system: named so, not as a permission
    that a chmod could change."""
    if folder is None:
        return []
    test, train = str(files["test-32"]), str(files["train-32"])
    scores = folder.parent / "read-only-scores.csv"
    assert main(["score", "--model", "random", "--data", test, "--out", str(scores), "--quiet"]) == 0
    said = f"cannot write to {folder}: read-only file system"
    return [
        (["generate", "--split", "test", "--pairs", "1", "--size", "32", "--out", str(folder / "g.h5"), "--quiet"],
         said),
        (["score", "--model", "random", "--data", test, "--out", str(folder / "s.csv"), "--quiet"], said),
        (["train", "perception", "--data", train, "--out", str(folder / "run"), "--steps", "1", "--quiet"], said),
        (["metrics", str(scores), "--rounds", "20", "--out", str(folder / "r")], said),
        (["show", test, "--out", str(folder / "s.png")], said),
        (["encode", "--model", "xpl", "--data", train, "--out", str(folder / "enc"), "--quiet"], said),
    ]


def test_every_bad_input_gets_one_line_exit_2_and_changes_nothing(files, tmp_path, capsys, monkeypatch, full_disk,
                                                                   read_only):
    monkeypatch.chdir(tmp_path)
    tried = 0
    full = full_disk_cases(files, full_disk) + read_only_cases(files, read_only)
    for args, needle in case_lines(files, tmp_path) + limit_cases(files, tmp_path) + full:
        before = snapshot(tmp_path)
        code, err = run(args, capsys)
        assert code == 2, (args, err)
        assert len(err.strip().splitlines()) == 1 and needle in err, (args, err)
        assert "Traceback" not in err
        assert snapshot(tmp_path) == before, args
        tried += 1
    assert tried == 6 * len(MALFORMED) + 2 * len(MALFORMED_TRAIN) + 40 + 31 + 14 + 6 + 7 + 7 + 17 + 14 + 6 + 5 + 23 \
        + len(full)
    assert full or (full_disk is None and read_only is None)


CONFIGS = (TrainConfig, PerceptionConfig, XPLConfig, ReasoningConfig, DynamicsConfig, PhyDNetConfig, InferenceConfig,
           GenerateConfig)


def _numeric(kind) -> bool:
    return any(t in (int, float) for t in (kind, *typing.get_args(kind)))


NUMERIC = [(cls, item.name) for cls in CONFIGS for item in fields(cls) if _numeric(field_type(cls, item.name))]


def test_every_numeric_field_declares_its_domain():
    assert len(NUMERIC) > 60
    assert [f"{cls.__name__}.{name}" for cls, name in NUMERIC if _domain_of(cls, name) is None] == []


@hypothesis_settings(max_examples=300, deadline=None)
@given(field=st.sampled_from(NUMERIC), value=st.one_of(st.floats(), st.integers(-2**80, 2**80)))
def test_any_number_in_any_field_is_in_its_domain_or_refused_by_name(field, value):
    cls, name = field
    domain = _domain_of(cls, name)
    try:
        parsed = parse_field(cls, name, repr(value))
    except XvoeError as error:
        assert str(error).startswith(f"{name}") and "\n" not in str(error)
    else:
        assert all(domain.holds(item) for item in (parsed if isinstance(parsed, tuple) else (parsed,)))
    kind = field_type(cls, name)
    if kind in (int, float) and isinstance(value, kind if kind is int else (int, float)):
        held = cls() if cls is not GenerateConfig else GenerateConfig("test")
        try:
            changed = override(held, **{name: value})
        except XvoeError as error:
            assert name in str(error) and "\n" not in str(error)
        else:
            assert domain.holds(getattr(changed, name))


def test_a_link_at_the_output_is_replaced_not_its_target(files, tmp_path):
    other = tmp_path / "other.csv"
    other.write_text("another command's result")
    (tmp_path / "link.csv").symlink_to(other)
    assert main(["score", "--model", "random", "--data", str(files["test"]), "--out", str(tmp_path / "link.csv"),
                 "--overwrite", "--quiet"]) == 0
    assert other.read_text() == "another command's result"
    assert not (tmp_path / "link.csv").is_symlink() and read_scores(tmp_path / "link.csv")["score"].size


UNPRIVILEGED = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
NOBODY = 65534
needs_setpriv = pytest.mark.skipif(shutil.which("setpriv") is None or os.geteuid() != 0,
                                   reason="needs setpriv, run as root")


def home_of_nobody(root: Path) -> Path:
    return root.with_name(root.name + "-home")


def run_unprivileged(root: Path, args: list[str]) -> subprocess.CompletedProcess:
    """`xvoe ARGS` as the user nobody, in `root`: root passes every permission check."""
    xvoe = str(Path(sys.executable).with_name("xvoe"))
    return subprocess.run(UNPRIVILEGED + [xvoe, *args], capture_output=True, text=True, cwd=root, timeout=300,
                          env=os.environ | {"OMP_NUM_THREADS": "1", "HOME": str(home_of_nobody(root))})


@pytest.fixture
def shared_folder(files):
    """A folder outside pytest's root-only one, holding a test split everyone may read, and
    a home of its own for the user nobody (matplotlib keeps its cache there)."""
    root = Path(tempfile.mkdtemp(prefix="xvoe-unwritable-"))
    root.chmod(0o755)
    home_of_nobody(root).mkdir(mode=0o777)
    os.chown(home_of_nobody(root), NOBODY, NOBODY)
    shutil.copy(files["test"], root / "test.h5")
    (root / "test.h5").chmod(0o644)
    yield root
    shutil.rmtree(root)
    shutil.rmtree(home_of_nobody(root))


@needs_setpriv
def test_a_directory_the_user_may_not_write_to_gets_one_line(shared_folder):
    root, data = shared_folder, str(shared_folder / "test.h5")
    (root / "locked").mkdir(mode=0o555)
    for args in (["score", "--model", "random", "--data", data, "--out", str(root / "locked" / "s.csv")],
                 ["generate", "--split", "test", "--pairs", "1", "--out", str(root / "locked" / "g.h5")],
                 ["train", "perception", "--data", data, "--out", str(root / "locked" / "run")],
                 ["show", data, "--out", str(root / "locked" / "s.png")]):
        before = snapshot(root)
        done = run_unprivileged(root, args)
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, (args, done.stderr)
        assert "permission denied" in done.stderr and "Traceback" not in done.stderr
        assert snapshot(root) == before


@needs_setpriv
def test_a_latent_cache_the_split_folder_refuses_is_named_before_the_work(shared_folder):
    """xvoe score makes a split's latent cache beside the split: a folder the user may not write
    to is named before the work, and --cache puts the cache elsewhere."""
    locked, home = shared_folder / "locked", home_of_nobody(shared_folder)
    locked.mkdir()
    generate(GenerateConfig("test", pairs=1, seed=2), locked / "t.h5", workers=1, progress=False)
    (locked / "t.h5").chmod(0o644)
    locked.chmod(0o555)
    score = ["score", "--model", "xpl", "--data", str(locked / "t.h5"), "--out", str(home / "s.csv"), "--quiet"]
    before = snapshot(shared_folder)
    done = run_unprivileged(shared_folder, score)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert f"cannot write to {locked}: permission denied" in done.stderr and "Traceback" not in done.stderr
    assert snapshot(shared_folder) == before and not list(home.glob("s.*"))
    done = run_unprivileged(shared_folder, score + ["--cache", str(home / "t.latents.h5")])
    assert done.returncode == 0 and (home / "t.latents.h5").is_file(), done.stderr


@needs_setpriv
def test_a_scores_file_the_user_may_not_replace_is_refused_before_the_work(shared_folder):
    # in a sticky folder (as /tmp) a user may replace their own curves but not another user's CSV;
    # should the folder refuse at the end all the same, both stay (test_a_set_of_files_is_replaced_...)
    folder = shared_folder / "sticky"
    folder.mkdir()
    folder.chmod(0o1777)
    (folder / "s.csv").write_text("root's scores")
    (folder / "s.curves.npz").write_text("nobody's curves")
    os.chown(folder / "s.curves.npz", NOBODY, NOBODY)
    before = snapshot(shared_folder)
    done = run_unprivileged(shared_folder, ["score", "--model", "random", "--data", "test.h5", "--out",
                                            str(folder / "s.csv"), "--overwrite", "--quiet"])
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert f"cannot replace {folder / 's.csv'}: it is another user's" in done.stderr
    assert "Traceback" not in done.stderr
    assert snapshot(shared_folder) == before


def test_a_set_of_files_is_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    old = [tmp_path / "r.curves.npz", tmp_path / "r.csv"]
    for path in old:
        path.write_text(f"old {path.name}")
    replace = os.replace

    def refuse_the_csv(source, target):
        if Path(source) == old[1]:
            raise PermissionError(1, "Operation not permitted")
        replace(source, target)

    monkeypatch.setattr(os, "replace", refuse_the_csv)
    before = snapshot(tmp_path)
    with pytest.raises(XvoeError, match="cannot replace .*r.csv: operation not permitted"):
        with atomic_paths(*old) as temporaries:
            for temporary in temporaries:
                temporary.write_text("new")
    assert snapshot(tmp_path) == before
    monkeypatch.setattr(os, "replace", replace)
    with atomic_paths(*old) as temporaries:
        for temporary in temporaries:
            temporary.write_text("new")
    assert [path.read_text() for path in old] == ["new", "new"] and len(list(tmp_path.iterdir())) == 2


def test_an_old_file_moved_aside_by_a_killed_process_goes_back(tmp_path):
    target = tmp_path / "r.csv"
    (tmp_path / ".r.csv.old-999999999").write_text("the old scores")
    remove_stale_temporaries(target)
    assert target.read_text() == "the old scores" and len(list(tmp_path.iterdir())) == 1


def test_a_stale_latent_cache_of_another_split_is_refused(files, tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    arrays = {name: np.zeros((2, 1, 1), np.float32) for name in ("mean", "std", "visible", "present", "pixels",
                                                                   "background_mean", "background_std")}
    config = '{"data": {"split": "train", "videos": 7}}'
    _write_latents(run_dir / "latents-train.h5", _Latents(**arrays, attrs={"source": "/elsewhere/train.h5",
                                                                          "source_split": "train",
                                                                          "config": config}))
    before = snapshot(tmp_path)
    code, err = run(["train", "xpl", "--data", str(files["train"]), "--out", str(run_dir), "--steps", "2"], capsys)
    assert code == 2 and "was encoded from /elsewhere/train.h5" in err
    assert snapshot(tmp_path) == before


def test_a_diverged_stage_saves_no_checkpoint_and_keeps_the_last_good_one(files, tmp_path, capsys):
    run_dir = tmp_path / "run"
    train = ["train", "perception", "--data", str(files["train"]), "--out", str(run_dir), "--set",
             "model.image_size=64", "--quiet"]
    code, err = run(train + ["--steps", "2", "--lr", "1e4"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert "the perception stage diverged by step 2" in err and "lower --lr than 10000" in err
    assert not (run_dir / "perception.pt").exists()
    assert run(train + ["--steps", "1", "--overwrite"], capsys)[0] == 0
    good = (run_dir / "perception.pt").read_bytes()
    code, err = run(train + ["--steps", "3", "--lr", "1e4", "--resume"], capsys)
    assert code == 2 and "diverged by step 3" in err, err
    assert (run_dir / "perception.pt").read_bytes() == good


def test_a_scores_file_and_its_curves_are_written_together(files, tmp_path):
    out = tmp_path / "r.csv"
    assert main(["score", "--model", "random", "--data", str(files["test"]), "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv", "r.curves.npz"]
    out.unlink()      # the curves alone still block a new result without --overwrite
    assert main(["score", "--model", "random", "--data", str(files["test"]), "--out", str(out), "--quiet"]) == 2
    assert not out.exists()


def test_a_rerun_report_leaves_nothing_of_the_last_one(files, tmp_path):
    scores = tmp_path / "random.csv"
    assert main(["score", "--model", "random", "--data", str(files["test"]), "--out", str(scores), "--quiet"]) == 0
    report = tmp_path / "report"
    assert main(["metrics", str(scores), "--out", str(report), "--rounds", "10"]) == 0
    (report / "components-gone.png").write_bytes(b"a figure of a model no longer reported")
    assert main(["metrics", str(scores), "--out", str(report), "--rounds", "10"]) == 2
    assert main(["metrics", str(scores), "--out", str(report), "--rounds", "10", "--overwrite"]) == 0
    assert not (report / "components-gone.png").exists() and (report / "metrics.csv").exists()


def test_temporaries_of_dead_processes_are_removed(tmp_path):
    target = tmp_path / "t.h5"
    dead, alive = tmp_path / ".t.h5.tmp-999999999", tmp_path / f".t.h5.tmp-{os.getpid()}"
    dead.write_bytes(b"half")
    alive.write_bytes(b"being written")
    remove_stale_temporaries(target)
    assert not dead.exists() and alive.exists()


HOLDER = """
import sys
from xvoe.outputs import claim_file, release, temporary_name
out = claim_file(sys.argv[1])
temporary_name(out).write_text("being written")
print("held", flush=True)
sys.stdin.readline()
release(out)
print("released", flush=True)
sys.stdin.readline()
"""


def held_elsewhere(out: Path) -> subprocess.Popen:
    """Another process that claims `out` and starts writing it, as a run does; a line on its
    stdin lets the claim go."""
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)
    assert holder.stdout.readline() == "held\n"
    return holder


def test_an_output_held_by_a_run_is_refused_in_one_line_until_it_is_let_go(files, tmp_path, capsys):
    scores, split, run_dir = tmp_path / "r.csv", tmp_path / "t.h5", tmp_path / "run"
    runs = {scores: ["score", "--model", "random", "--data", str(files["test"]), "--out", str(scores), "--quiet"],
            split: ["generate", "--split", "train", "--videos", "2", "--out", str(split), "--quiet"],
            run_dir / "perception.pt": ["train", "perception", "--data", str(files["train"]), "--out", str(run_dir),
                                        "--steps", "1", "--set", "model.image_size=64", "--quiet"]}
    holders = {target: held_elsewhere(target) for target in runs}
    try:
        before = snapshot(tmp_path)
        for target, args in runs.items():
            for overwrite in ([], ["--overwrite"]):     # overwriting replaces a finished file, not a run's
                code, err = run(args + overwrite, capsys)
                assert code == 2 and len(err.strip().splitlines()) == 1, err
                assert f"{target} is being written by another run (process {holders[target].pid})" in err
        assert snapshot(tmp_path) == before         # the first run's claim and its half-written file untouched
        holders[scores].stdin.write("\n")
        holders[scores].stdin.flush()
        assert holders[scores].stdout.readline() == "released\n"
        assert run(runs[scores], capsys)[0] == 0
        writing = tmp_path / f".r.csv.tmp-{holders[scores].pid}"
        assert scores.is_file() and writing.read_text() == "being written"     # its writer lives: left alone
    finally:
        for holder in holders.values():
            holder.kill()
            holder.wait()


def test_a_claim_of_a_run_killed_with_sigkill_blocks_no_later_run(files, tmp_path, capsys):
    out = tmp_path / "r.csv"
    holder = held_elsewhere(out)
    holder.kill()       # SIGKILL: no cleanup runs
    holder.wait()
    assert run(["score", "--model", "random", "--data", str(files["test"]), "--out", str(out), "--quiet"],
               capsys)[0] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.csv", "r.curves.npz"]     # its claim and temporary gone


WAITING_MODEL = """
import os
import time
from pathlib import Path


class Waiting:
    name = "waiting"

    def surprise(self, videos):
        Path(__file__).with_name(f"scoring-{os.getpid()}").touch()      # a worker is scoring
        time.sleep(3600)
"""


def running(pid: int) -> bool:
    """Whether process `pid` runs (a zombie no longer does)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def children_of(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        with contextlib.suppress(OSError, IndexError):
            if entry.name.isdigit() and int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(entry.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")
def test_a_score_in_workers_killed_with_sigkill_leaves_no_process_and_its_parts_go(files, tmp_path):
    model = tmp_path / "waiting.py"
    model.write_text(WAITING_MODEL)
    out = tmp_path / "scores" / "r.csv"
    scoring = subprocess.Popen([sys.executable, "-m", "xvoe", "score", "--model", f"{model}:Waiting", "--data",
                                str(files["test"]), "--out", str(out), "--workers", "2", "--no-checks", "--quiet"],
                               stderr=subprocess.DEVNULL)
    while len(list(tmp_path.glob("scoring-*"))) < 2:
        assert scoring.poll() is None, "the run ended before both workers scored"
        time.sleep(0.1)
    children = children_of(scoring.pid)       # the two workers and multiprocessing's resource tracker
    assert len(children) == 3
    scoring.kill()
    scoring.wait()
    for _ in range(600):
        if not any(map(running, children)):
            break
        time.sleep(0.1)
    assert not [pid for pid in children if running(pid)]
    assert [p.name for p in out.parent.glob(".r.csv.parts-*")] == [f".r.csv.parts-{scoring.pid}"]
    assert main(["score", "--model", "random", "--data", str(files["test"]), "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.csv", "r.curves.npz"]


@hypothesis_settings(max_examples=25, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(drop=st.sampled_from(["rgbd", "ids", "states", "kind", "color", "scenario", "setting", "pair", "member",
                             "possible", "event_frame"]),
       how=st.sampled_from(["delete", "truncate", "retype"]))
def test_any_broken_dataset_is_named_on_opening(files, tmp_path, drop, how):
    def change(file):
        if how == "delete":
            del file[drop]
        elif how == "truncate":
            _replace(file, drop, file[drop][:3])
        else:
            _replace(file, drop, np.full(file[drop].shape[:1] + (2,), 1.5))
    path = mutate(files["test"], tmp_path / f"{drop}-{how}.h5", change)
    with pytest.raises(XvoeError, match=drop):
        store.open_dataset(path).close()


LABEL_EDITS = {"scenario": ["collision", "permanence", "telekinesis", ""], "setting": ["S1", "S2", "S3", "S4"],
               "pair": [-1, 0, 1, 999], "member": [0, 1, 2], "possible": [True, False],
               "event_frame": [-2, -1, 0, 14, 15]}


@hypothesis_settings(max_examples=80, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(edits=st.lists(st.tuples(st.integers(0, 200), st.sampled_from(sorted(LABEL_EDITS)), st.integers(0, 4)),
                      max_size=3))
def test_labels_a_split_may_hold_are_labels_the_metrics_can_read(files, edits):
    """Whatever test labels opening a split lets through, the metrics take as they are: every
    pair whole, every scenario and setting known."""
    with store.open_dataset(files["test"]) as file:
        found, frames = store.labels(file, store.TEST_LABELS), file["rgbd"].shape[1]
    for row, name, choice in edits:
        found[name][row % len(found[name])] = LABEL_EDITS[name][choice % len(LABEL_EDITS[name])]
    problem = store.pair_labels_problem(found, frames)
    if problem is not None:
        assert problem.startswith("labels video") and "\n" not in problem
        return
    count = len(found["pair"])
    table = {"index": np.arange(count, dtype=float), "score": np.zeros(count), "possible": found["possible"],
             "scenario": found["scenario"], "setting": found["setting"], "pair": found["pair"].astype(float),
             "member": found["member"].astype(float)}
    assert score_problem(table) is None
    assert np.all((found["event_frame"] >= -1) & (found["event_frame"] < frames))


# --- score files from anywhere ----------------------------------------------------------

def write_scores(path: Path, rows: list[dict]) -> Path:
    fields = list(rows[0]) if rows else ["index", "score"]
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fields)
        writer.writeheader()
        writer.writerows(rows)
    return path


@pytest.fixture(scope="module")
def labelled(files):
    """A good scores table of the test split, as rows."""
    with store.open_dataset(files["test"]) as file:
        labels = {name: (store.strings(file, name) if name in ("scenario", "setting") else file[name][:])
                  for name in ("scenario", "setting", "pair", "member", "possible")}
    rng = np.random.default_rng(0)
    return [{"index": i, "scenario": labels["scenario"][i], "setting": labels["setting"][i],
             "pair": int(labels["pair"][i]), "member": int(labels["member"][i]),
             "possible": bool(labels["possible"][i]), "score": float(rng.random())}
            for i in range(len(labels["pair"]))]


def with_change(rows: list[dict], change) -> list[dict]:
    rows = [dict(r) for r in rows]
    change(rows)
    return rows


BAD_SCORES = {
    "one NaN": (lambda rows: rows[3].update(score="nan"), "not a finite number"),
    "all NaN": (lambda rows: [r.update(score="nan") for r in rows], "not a finite number"),
    "members all 0": (lambda rows: [r.update(member=0) for r in rows], "same member twice"),
    "possible maybe": (lambda rows: rows[0].update(possible="maybe"), "possible must be true or false"),
    "duplicate row": (lambda rows: rows.append(dict(rows[5])), "more than one row"),
    "pair without partner": (lambda rows: rows.pop(1), "has one member"),
    "unknown scenario": (lambda rows: [r.update(scenario="juggling") for r in rows[:2]], "unknown scenario"),
    "non-numeric score": (lambda rows: rows[2].update(score="high"), "not a number"),
    "no score column": (lambda rows: [r.pop("score") for r in rows], "no column(s) score"),
}


def test_every_bad_scores_file_gets_one_line_exit_2_and_writes_nothing(labelled, files, tmp_path, capsys):
    cases = [(write_scores(tmp_path / f"{name}.csv", with_change(labelled, change)), [], needle)
             for name, (change, needle) in BAD_SCORES.items()]
    binary = tmp_path / "binary.csv"
    binary.write_bytes(bytes(range(256)) * 4)
    cases.append((binary, [], "not a CSV text file"))
    just_scores = write_scores(tmp_path / "just.csv", [{"index": r["index"], "score": r["score"]} for r in labelled])
    cases.append((just_scores, [], "give --data"))
    other = tmp_path / "other.h5"
    main(["generate", "--split", "test", "--pairs", "7", "--seed", "4", "--out", str(other), "--quiet"])
    cases.append((write_scores(tmp_path / "good.csv", labelled), ["--data", str(other)], "does not hold the videos"))
    missing = write_scores(tmp_path / "missing.csv", [{"index": r["index"], "score": r["score"]} for r in labelled][1:])
    cases.append((missing, ["--data", str(files["test"])], "video 0 is missing"))
    for path, extra, needle in cases:
        before = snapshot(tmp_path)
        code, err = run(["metrics", str(path), "--out", str(tmp_path / "report"), "--rounds", "5", *extra], capsys)
        assert code == 2 and len(err.strip().splitlines()) == 1 and needle in err, (path.name, err)
        assert snapshot(tmp_path) == before


def test_index_and_score_alone_are_joined_with_the_split(labelled, files, tmp_path):
    just = write_scores(tmp_path / "just.csv", [{"index": r["index"], "score": r["score"]} for r in labelled[::-1]])
    joined = read_scores(just, files["test"])
    full = read_scores(write_scores(tmp_path / "full.csv", labelled))
    order = np.argsort(joined["index"])
    for name in ("scenario", "setting", "pair", "member", "possible", "score"):
        assert np.array_equal(joined[name][order], full[name]), name


@hypothesis_settings(max_examples=40, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(edits=st.lists(st.tuples(st.integers(0, 200), st.sampled_from(["index", "scenario", "setting", "pair",
                                                                       "member", "possible", "score"]),
                                st.sampled_from(["", "nan", "inf", "-1", "0", "1", "2.5", "x", "S9", "true",
                                                 "collision", "1e400"])), max_size=4),
       drop=st.integers(0, 300))
def test_a_randomly_broken_scores_file_is_read_whole_or_refused_in_one_line(labelled, tmp_path, edits, drop):
    rows = [dict(r) for r in labelled]
    for row, column, value in edits:
        rows[row % len(rows)][column] = value
    if drop < len(rows):
        rows.pop(drop)
    path = write_scores(tmp_path / "random.csv", rows)
    try:
        scores = read_scores(path)
    except XvoeError as error:
        assert "\n" not in str(error)
    else:
        assert score_problem(scores) is None


def test_a_name_the_file_system_takes_is_written_however_long(tmp_path, capsys):
    """A 250-byte name is legal: its temporaries and claim, beside it, are shorter than it."""
    out = tmp_path / ("g" * 247 + ".h5")
    picture = tmp_path / ("p" * 246 + ".png")
    assert run(["generate", "--split", "test", "--pairs", "1", "--size", "16", "--out", str(out), "--quiet"],
               capsys)[0] == 0
    assert run(["show", str(out), "--out", str(picture)], capsys)[0] == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, picture.name])
    store.open_dataset(out).close()


LOSES_THE_FOLDER = """
import os
import subprocess

import numpy as np


class LosesTheFolder:
    name = "loses-the-folder"
    changed = False

    def surprise(self, videos):
        if not self.changed:
            {change}
            self.changed = True
        return np.zeros((len(videos.index), videos.frames))
"""


def lose_the_folder_midway(root: Path, change: str) -> list[str]:
    """`xvoe score` arguments whose model, as it scores, makes the folder of --out refuse writes."""
    (root / "loses.py").write_text(LOSES_THE_FOLDER.format(change=change))
    (root / "loses.py").chmod(0o644)
    return ["score", "--model", f"{root / 'loses.py'}:LosesTheFolder", "--data", str(root / "test.h5"),
            "--out", str(root / "out" / "s.csv"), "--no-checks", "--quiet"]


def test_a_folder_made_read_only_as_score_runs_gets_one_line_and_no_scores(files, tmp_path, capsys):
    if os.geteuid() != 0:
        pytest.skip("mounts a folder read-only: run as root")
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(files["test-32"], tmp_path / "test.h5")
    # a read-only mount of the folder over itself: the run's open claim is on the one below
    args = lose_the_folder_midway(tmp_path, f"subprocess.run(['mount', '--bind', {str(out)!r}, {str(out)!r}]); "
                                            f"subprocess.run(['mount', '-o', 'remount,bind,ro', {str(out)!r}])")
    try:
        code, err = run(args, capsys)
    finally:
        while subprocess.run(["umount", str(out)], capture_output=True).returncode == 0:
            pass
    assert code == 2 and err == f"xvoe score: error: read-only file system writing {out / 's.csv'}\n", err
    assert all(path.name.startswith(".") for path in out.iterdir())      # claims, which the next run takes
    args[args.index("--model") + 1] = "random"
    assert run(args, capsys)[0] == 0
    assert sorted(path.name for path in out.iterdir()) == ["s.csv", "s.curves.npz"]


@needs_setpriv
def test_a_folder_made_unwritable_as_score_runs_gets_one_line_and_no_scores(files, shared_folder):
    out = shared_folder / "out"
    out.mkdir()
    os.chown(out, NOBODY, NOBODY)
    args = lose_the_folder_midway(shared_folder, f"os.chmod({str(out)!r}, 0o555)")
    done = run_unprivileged(shared_folder, args)
    assert done.returncode == 2 and done.stderr == f"xvoe score: error: permission denied writing {out / 's.csv'}\n", \
        done.stderr
    assert all(path.name.startswith(".") for path in out.iterdir())
