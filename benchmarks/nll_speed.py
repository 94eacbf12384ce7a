"""The NLL's speed against an earlier commit's, in one process, and how far each video's NLL moved.

    python benchmarks/nll_speed.py --model xpl --data fresh4.h5 --before COMMIT [--videos 48] [--rounds 3]
                                   [--particles 64] [--threads 1] [--seed 0]

The `inference/` package of git commit COMMIT is read with `git show` (nothing is checked out)
and imported beside this tree's as a package of its own; both estimate the NLL of the same
encoded and drawn videos (the first N of the split, as `xvoe score --surprise nll` draws them,
encoding excluded) with the same seed, in alternating rounds, so that other jobs on the machine
slow both alike. The ratio of the two is the figure to read on a shared machine.
Last line: before_videos_per_s=N.NN after_videos_per_s=N.NN speedup=N.NN max_nll_difference=N.Ne-N
"""
from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

import xvoe
from inference.score import nll_config, xpl_nll
from xvoe.benchmark import store
from xvoe.errors import XvoeError
from xvoe.evaluation.score import encode_videos
from xvoe.evaluation.surprise import draw_scene
from xvoe.models.nll import InferenceConfig
from xvoe.training.data import check_size

ROOT = Path(__file__).resolve().parent.parent
BATCH = 16


def inference_at(commit: str, folder: Path) -> ModuleType:
    """`inference.score` as it was at `commit`, imported as `inference_COMMIT.score`."""
    def git(*args: str) -> str:
        done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True)
        if done.returncode != 0:
            raise XvoeError(f"git {' '.join(args)}: {done.stderr.strip()}")
        return done.stdout

    name = f"inference_{git('rev-parse', '--short', commit).strip()}"
    package = folder / name
    package.mkdir()
    for path in git("ls-tree", "--name-only", commit, "inference/").split():
        if path.endswith(".py"):
            (package / Path(path).name).write_text(git("show", f"{commit}:{path}"))
    sys.path.insert(0, str(folder))
    return importlib.import_module(f"{name}.score")


def drawn_batches(scorer, data: str, videos: int) -> list[tuple[dict, object]]:
    """The first `videos` videos, encoded and drawn in batches as `xvoe score` does."""
    with store.open_dataset(data) as file:
        check_size(file, scorer.image_size, f"the model {scorer.name}")
        count = min(videos, file["rgbd"].shape[0])
        batches = []
        for start in range(0, count, BATCH):
            batch = encode_videos(scorer, file, start, min(count, start + BATCH), None)
            scene = draw_scene(scorer.vae, scorer.xpl, batch["mean"], batch["visible"], batch["background"],
                               batch["occluder"])
            batches.append((batch, scene))
    return batches


def timed(estimate, scorer, batches, config: InferenceConfig, seed: int) -> tuple[float, np.ndarray, np.ndarray]:
    """Seconds for every video's NLL, the NLLs (N,) and the per-frame curves (N, T)."""
    tick = time.perf_counter()
    found = [f for batch, scene in batches for f in estimate(scorer, batch, config, seed, scene)]
    seconds = time.perf_counter() - tick
    return seconds, np.array([f.nll for f in found]), np.stack([f.frame_nll.numpy() for f in found])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="xpl", help="a shipped model's name, a run directory or checkpoint")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--before", required=True, help="the git commit whose inference/ to compare with")
    parser.add_argument("--videos", type=int, default=48, help="the first N videos of the split (default 48)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of both (default 3)")
    parser.add_argument("--particles", type=int, help="particles per video (default: the model's settings)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    try:
        run(args)
    except XvoeError as error:
        raise SystemExit(f"nll_speed.py: error: {error}") from None


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    scorer = xvoe.load_model(args.model)
    config = nll_config(scorer.nll or InferenceConfig(), args.particles)
    batches = drawn_batches(scorer, args.data, args.videos)
    videos = sum(len(batch["mean"]) for batch, _ in batches)
    with tempfile.TemporaryDirectory() as folder:
        before = inference_at(args.before, Path(folder)).xpl_nll
        seconds, found = {"before": [], "after": []}, {}
        for round_ in range(args.rounds):
            order = [("before", before), ("after", xpl_nll)]
            for name, estimate in order if round_ % 2 == 0 else order[::-1]:
                spent, *found[name] = timed(estimate, scorer, batches, config, args.seed)
                seconds[name].append(spent)
            print(f"round {round_ + 1}: before {videos / seconds['before'][-1]:.2f}, after "
                  f"{videos / seconds['after'][-1]:.2f} videos/s ({seconds['before'][-1] / seconds['after'][-1]:.2f}x)")
    (nll_a, curves_a), (nll_b, curves_b) = found["before"], found["after"]
    difference = np.abs(nll_b - nll_a)
    relative = difference / np.abs(nll_a)
    ratios = np.array(seconds["before"]) / np.array(seconds["after"])
    rate_before, rate_after = videos / np.median(seconds["before"]), videos / np.median(seconds["after"])
    print(f"model {args.model}, {args.data}: {videos} videos, {config.particles} particles, seed {args.seed}, "
          f"{args.threads} thread(s), before = {args.before}")
    print(f"median of {args.rounds} rounds: before {rate_before:.2f}, after {rate_after:.2f} videos/s; "
          f"per-round speedups {', '.join(f'{r:.2f}' for r in ratios)} (median {np.median(ratios):.2f})")
    print(f"|NLL after - NLL before| per video: largest {difference.max():.2e} nats (relative {relative.max():.1e}), "
          f"median {np.median(difference):.1e}; per-frame curves: largest {np.abs(curves_b - curves_a).max():.2e}")
    print(f"before_videos_per_s={rate_before:.2f} after_videos_per_s={rate_after:.2f} "
          f"speedup={np.median(ratios):.2f} max_nll_difference={difference.max():.1e}")


if __name__ == "__main__":
    main()
