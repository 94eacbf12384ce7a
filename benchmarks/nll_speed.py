"""The NLL's speed against an earlier commit's, in one process, and how far each video's NLL moved.

    python benchmarks/nll_speed.py --model xpl --data fresh4.h5 --before COMMIT [--videos 48] [--rounds 3]
                                   [--particles 64] [--threads 1] [--seed 0]

The `inference/` package of git commit COMMIT is read with `git show` (nothing is checked out)
and imported beside this tree's as a package of its own; both estimate the NLL of the same
encoded and drawn videos (the first N of the split, as `xvoe score --surprise nll` draws them,
encoding excluded) with the same seed, interleaved batch by batch (the first of the two
alternating), so that other jobs on the machine slow both alike. The ratios of the two, of wall
and of CPU time, are the figures to read on a shared machine.
Last line: before_videos_per_s=N.NN after_videos_per_s=N.NN speedup=N.NN cpu_speedup=N.NN
max_nll_difference=N.Ne-N
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
from xvoe.evaluation.scorer import encode_videos
from xvoe.evaluation.surprise import draw_scene
from xvoe.inference.score import nll_config, xpl_nll
from xvoe.models.nll import InferenceConfig
from xvoe.training.data import check_size
from xvoe.training.stages import XPL

ROOT = Path(__file__).resolve().parent.parent
BATCH = 16


def inference_at(commit: str, folder: Path) -> ModuleType:
    """`inference.score` as it was at `commit`, imported as `inference_COMMIT.score`."""
    def git(*args: str) -> str:
        done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True)
        if done.returncode != 0:
            raise xvoe.XvoeError(f"git {' '.join(args)}: {done.stderr.strip()}")
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
    with xvoe.open_dataset(data) as file:
        check_size(file, scorer.image_size, f"the model {scorer.name}")
        count = min(videos, file["rgbd"].shape[0])
        batches = []
        for start in range(0, count, BATCH):
            batch = encode_videos(scorer, file, start, min(count, start + BATCH), None)
            scene = draw_scene(scorer.vae, scorer.xpl, batch["mean"], batch["visible"], batch["background"],
                               batch["occluder"])
            batches.append((batch, scene))
    return batches


def timed(estimate, scorer, batch: dict, scene, config: InferenceConfig, seed: int) -> tuple[float, float, list]:
    """Wall and CPU seconds for one batch's NLLs, and the estimates."""
    tick, cpu = time.perf_counter(), time.process_time()
    found = estimate(scorer, batch, config, seed, scene)
    return time.perf_counter() - tick, time.process_time() - cpu, found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=XPL, help="a shipped model's name, a run directory or checkpoint")
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
    except xvoe.XvoeError as error:
        raise SystemExit(f"nll_speed.py: error: {error}") from None


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    scorer = xvoe.load_model(args.model)
    config = nll_config(scorer.nll or InferenceConfig(), args.particles)
    batches = drawn_batches(scorer, args.data, args.videos)
    videos = sum(len(batch["mean"]) for batch, _ in batches)
    with tempfile.TemporaryDirectory() as folder:
        estimates = {"before": inference_at(args.before, Path(folder)).xpl_nll, "after": xpl_nll}
        # (rounds, 2): wall and CPU seconds of each round's pass over every video
        spent = {name: np.zeros((args.rounds, 2)) for name in estimates}
        found: dict[str, list] = {}
        for round_ in range(args.rounds):
            for number, (batch, scene) in enumerate(batches):     # interleaved batch by batch, first one then the other
                names = list(estimates) if (round_ + number) % 2 == 0 else list(estimates)[::-1]
                for name in names:
                    wall, cpu, estimate = timed(estimates[name], scorer, batch, scene, config, args.seed)
                    spent[name][round_] += (wall, cpu)
                    if round_ == 0:
                        found.setdefault(name, []).extend(estimate)
            before, after = spent["before"][round_], spent["after"][round_]
            print(f"round {round_ + 1}: before {videos / before[0]:.2f}, after {videos / after[0]:.2f} videos/s "
                  f"({before[0] / after[0]:.2f}x wall, {before[1] / after[1]:.2f}x CPU)")
    report(args, config, videos, spent, found)


def report(args: argparse.Namespace, config: InferenceConfig, videos: int, spent: dict[str, np.ndarray],
           found: dict[str, list]) -> None:
    """Print the figures; the last line is the summary."""
    nll = {name: np.array([f.nll for f in estimates]) for name, estimates in found.items()}
    curves = {name: np.stack([f.frame_nll.numpy() for f in estimates]) for name, estimates in found.items()}
    difference = np.abs(nll["after"] - nll["before"])
    relative = difference / np.abs(nll["before"])
    wall = spent["before"][:, 0] / spent["after"][:, 0]
    cpu = spent["before"][:, 1] / spent["after"][:, 1]
    rate = {name: videos / np.median(seconds[:, 0]) for name, seconds in spent.items()}
    cpu_rate = {name: videos / np.median(seconds[:, 1]) for name, seconds in spent.items()}
    print(f"model {args.model}, {args.data}: {videos} videos, {config.particles} particles, seed {args.seed}, "
          f"{args.threads} thread(s), before = {args.before}")
    print(f"median of {args.rounds} rounds: before {rate['before']:.2f}, after {rate['after']:.2f} videos/s "
          f"({cpu_rate['before']:.2f} and {cpu_rate['after']:.2f} per CPU-second); speedup per round "
          f"{', '.join(f'{r:.2f}' for r in wall)} wall, {', '.join(f'{r:.2f}' for r in cpu)} CPU")
    print(f"|NLL after - NLL before| per video: largest {difference.max():.2e} nats (relative {relative.max():.1e}), "
          f"median {np.median(difference):.1e}, {int((difference == 0).sum())} of {videos} the same bits; "
          f"per-frame curves: largest {np.abs(curves['after'] - curves['before']).max():.2e}")
    print(f"before_videos_per_s={rate['before']:.2f} after_videos_per_s={rate['after']:.2f} "
          f"speedup={np.median(wall):.2f} cpu_speedup={np.median(cpu):.2f} max_nll_difference={difference.max():.1e}")


if __name__ == "__main__":
    main()
