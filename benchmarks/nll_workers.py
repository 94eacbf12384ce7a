"""The NLL's scoring speed in one process against worker processes (`xvoe score --workers`).

    python benchmarks/nll_workers.py --model xpl --data val.h5 [--workers 2] [--particles 64]

Scores the whole split with `--surprise nll` twice: one process with every core's thread,
then `--workers` processes with the cores shared out. Prints the videos per second of each,
encoding included, their ratio, and the largest difference of a video's NLL between them (a
thread count changes a sum's order, nothing else). Last line:
one_process=N.N workers=N.N ratio=N.NN (the goal: >= 5 videos/s at 64 particles on 2 cores).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import xvoe
from xvoe.benchmark import store


def timed(model: str, data: str, out: Path, particles: int, workers: int) -> float:
    start = time.perf_counter()
    xvoe.score(model, data, out, surprise="nll", particles=particles, workers=workers, progress=False)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="xpl", help="a shipped model's name or a run directory")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--workers", type=int, default=len(os.sched_getaffinity(0)))
    parser.add_argument("--particles", type=int, default=64)
    args = parser.parse_args()
    torch.set_num_threads(len(os.sched_getaffinity(0)))
    with store.open_dataset(args.data) as file:
        videos = len(file["rgbd"])
    with tempfile.TemporaryDirectory() as work:
        one = timed(args.model, args.data, Path(work) / "one.csv", args.particles, 1)
        many = timed(args.model, args.data, Path(work) / "many.csv", args.particles, args.workers)
        apart = np.abs(np.asarray(xvoe.read_scores(Path(work) / "one.csv")["nll"])
                       - np.asarray(xvoe.read_scores(Path(work) / "many.csv")["nll"])).max()
    print(f"{videos} videos, {args.particles} particles, {len(os.sched_getaffinity(0))} cores; a video's NLL "
          f"differs between the runs by at most {apart:.1e} nats")
    print(f"one process, {torch.get_num_threads()} threads: {one:.1f} s; {args.workers} worker processes: {many:.1f} s")
    print(f"one_process={videos / one:.1f} workers={videos / many:.1f} ratio={one / many:.2f}")


if __name__ == "__main__":
    main()
