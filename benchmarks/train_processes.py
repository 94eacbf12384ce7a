"""A training stage's speed in one process with every core's thread against one one-thread
process per core (`xvoe.training.launch.on_cores`, what `xvoe pipeline` does).

    python benchmarks/train_processes.py --data train.h5 [--steps 150]

Trains the perception, XPL and proposal stages from nothing for --steps steps of the recipe,
both ways, in fresh run directories (both XPL runs on the latent cache that the first way's
perception encodes), and prints the items per second each way over the steps after the first
--skip (start-up and the first allocations left out), and their ratio. Time it on an idle
machine. Last three lines, one per stage: STAGE threads=N.N processes=N.N ratio=N.NN.
"""
from __future__ import annotations

import argparse
import csv
import os
import tempfile
from pathlib import Path

import torch

from xvoe.training.checkpoints import load_checkpoint
from xvoe.training.latents import encode_split
from xvoe.training.launch import on_cores
from xvoe.training.perception import train_perception
from xvoe.training.xpl import train_proposal, train_xpl

STAGES = ("perception", "xpl", "proposal")


def rate(run: Path, stage: str, skip: int) -> float:
    """Items per second over the logged steps after `skip`: the batch (summed over processes)
    times the steps, over the wall time between them (the loss CSV's minutes column)."""
    batch = load_checkpoint(run / f"{stage}.pt")["train"]["batch_size"]
    rows = [row for row in csv.DictReader(open(run / f"{stage}.csv")) if int(row["step"]) > skip]
    steps = int(rows[-1]["step"]) - int(rows[0]["step"])
    return batch * steps / (60 * (float(rows[-1]["minutes"]) - float(rows[0]["minutes"])))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="a training split at the recipe's resolution")
    parser.add_argument("--recipe", default="cpu")
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--skip", type=int, default=30, help="steps left out of the rate")
    args = parser.parse_args()
    cores = len(os.sched_getaffinity(0))
    common = dict(steps=args.steps, log_every=10, progress=False, overwrite=True)
    ways = {"threads": 1, "processes": cores}
    results = {}
    torch.set_num_threads(cores)
    os.environ["OMP_NUM_THREADS"] = str(cores)     # the one-process way: every core's thread
    with tempfile.TemporaryDirectory() as tmp:
        latents = Path(tmp) / "latents.h5"
        for way, processes in ways.items():
            run = Path(tmp) / way
            on_cores(train_perception, processes, data=args.data, run_dir=run, recipe_name=args.recipe, **common)
            if not latents.exists():        # both ways' XPL read the first way's latents
                encode_split(run, args.data, latents, overwrite=True, progress=False)
            on_cores(train_xpl, processes, latents=latents, run_dir=run, recipe_name=args.recipe, **common)
            on_cores(train_proposal, processes, run_dir=run, latents=latents, **common)     # the recipe of xpl.pt
            for stage in STAGES:
                results[stage, way] = rate(run, stage, args.skip)
                print(f"{stage:<11} {way:<9} ({processes} process(es)): {results[stage, way]:7.1f} items/s", flush=True)
    for stage in STAGES:
        threads, processes = results[stage, "threads"], results[stage, "processes"]
        print(f"{stage} threads={threads:.1f} processes={processes:.1f} ratio={processes / threads:.2f}")


if __name__ == "__main__":
    main()
