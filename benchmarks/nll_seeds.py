"""The NLL's spread between seeds on chosen videos of a test split: each video scored with every
seed under the model's NLL settings (changed by --nll-set), its NLL per seed, their spread
(max - min), the CPU seconds a run takes, and on how many videos each seed gives the highest NLL
(about as many for each where each video's draws are its own).

    python benchmarks/nll_seeds.py --model xpl --data test.h5 [--videos hidden | 160,162,...]
                                   [--seeds 0,1,2,3] [--threads 1] [--nll-set FIELD=VALUE ...] [--rows rows.csv]

--videos hidden (the default) takes every video of the split whose ground truth holds an object
visible in no frame (`xvoe.evaluation.explanation_quality.ground_truth`): the never-seen-cube
videos, where the two-seed tail lives.
Last line: videos=N spread_median=N.NN spread_max=N.NN mean_nll=N.NN cpu_per_run=N.NNN
"""
from __future__ import annotations

import argparse
import csv
import time

import numpy as np
import torch
from nll import arguments, run_or_exit

import xvoe
from xvoe.evaluation.explanation_quality import ground_truth
from xvoe.evaluation.scorer import encode_videos
from xvoe.inference.score import nll_config, nll_settings
from xvoe.inference.surprise import nll_surprise
from xvoe.models.nll import InferenceConfig
from xvoe.training.data import check_size


def chosen_videos(file, videos: str) -> list[int]:
    """The indices `videos` names: "hidden", or a comma-separated list."""
    if videos != "hidden":
        return [int(index) for index in videos.split(",")]
    return [index for index in range(len(file["possible"])) if ground_truth(file, index) == "hidden"]


@torch.no_grad()
def score(scorer, file, index: int, config: InferenceConfig, seeds: list[int]) -> dict:
    """One video's NLL with every seed and the mean CPU seconds of a run (encoding excluded)."""
    batch = encode_videos(scorer, file, index, index + 1)
    video = [batch[name][0] for name in ("frames", "mean", "visible", "background", "occluder")]
    row, cpu = {"index": index}, 0.0
    for seed in seeds:
        began = time.process_time()
        found = nll_surprise(scorer.vae, scorer.xpl, *video, config, seed=seed)
        cpu += time.process_time() - began
        row[f"nll_{seed}"] = found.nll
    nlls = [row[f"nll_{seed}"] for seed in seeds]
    return row | {"spread": max(nlls) - min(nlls), "mean_nll": float(np.mean(nlls)), "cpu_seconds": cpu / len(seeds)}


def main() -> None:
    parser = arguments(__doc__.splitlines()[0])
    parser.add_argument("--videos", default="hidden", help="'hidden' or comma-separated video indices")
    parser.add_argument("--seeds", default="0,1,2,3", help="comma-separated seeds (default 0,1,2,3)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    run_or_exit(run, parser.parse_args(), "nll_seeds.py")


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    seeds = [int(seed) for seed in args.seeds.split(",")]
    scorer = xvoe.load_model(args.model)
    config = nll_config(scorer.nll or InferenceConfig(), None, nll_settings(args.nll_set))
    with xvoe.open_dataset(args.data) as file:
        check_size(file, scorer.image_size, f"the model {scorer.name}")
        rows = [score(scorer, file, index, config, seeds) for index in chosen_videos(file, args.videos)]
    if args.rows:
        with open(args.rows, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    for row in rows:
        print(f"video {row['index']}: " + " ".join(f"{row[f'nll_{seed}']:.1f}" for seed in seeds)
              + f"  spread {row['spread']:.2f}  cpu {row['cpu_seconds']:.2f} s")
    spread = np.array([row["spread"] for row in rows])
    mean_nll = float(np.mean([row["mean_nll"] for row in rows]))
    cpu = float(np.mean([row["cpu_seconds"] for row in rows]))
    # where every video draws from one stream per seed, one seed is the worst on most videos at once
    worst = np.bincount([int(np.argmax([row[f"nll_{seed}"] for seed in seeds])) for row in rows], minlength=len(seeds))
    print("videos on which each seed gives the highest NLL: " + ", ".join(f"seed {seed} {count}"
                                                                         for seed, count in zip(seeds, worst)))
    print(f"{config}")
    print(f"videos={len(rows)} spread_median={np.median(spread):.2f} spread_max={spread.max():.2f} "
          f"mean_nll={mean_nll:.2f} cpu_per_run={cpu:.3f}")


if __name__ == "__main__":
    main()
