"""How far each full run's hidden-object branch trails where the existence head is sure of an
object: what decides `sure_margin`, the trail past which a sure video's first run ends it.

    python benchmarks/nll_sure.py --model xpl --data val.h5 [--runs 6] [--first 0] [--last N]
                                  [--cap N] [--truth hidden|seen|both] [--threads 1]

For every video of the split (indices --first to --last, at most --cap of them) with a slot free
for a hidden object and an existence probability above `smc_pilot_skip_exists` (the videos whose
runs are pooled), --runs full runs of the hidden-object branch are made as `_pooled_runs` makes
each (the explanations of what was seen stepped as one batch, around Transformer 2's mean moved
out of sight), each from a generator of its own. A run's trail is log p(x, no object) summed over
the explanations (exact) less the run's log p^(x, object), summed over them too. Two kinds of
video, by the split's ground truth:
- an object visible in no frame ("hidden"): a run that trails by more than the margin while
  another run of the video leads (trail < 0) is one a margin would wrongly end the video on;
- every object seen at some frame ("seen"): the head is wrongly sure, and a margin saves the
  other runs where the first run trails by more than it.
Last line: hidden_videos=N largest_miss_trail=N.N wrong_stops_M=N seen_videos=N smallest_seen_trail=N.N
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from tqdm.auto import tqdm

import xvoe
from xvoe.evaluation.explanation_quality import ground_truth
from xvoe.evaluation.scorer import encode_videos
from xvoe.evaluation.surprise import draw_scene
from xvoe.inference.evidence import widenings_of
from xvoe.inference.guide import out_of_sight
from xvoe.inference.model import HiddenObjectModel
from xvoe.inference.model_steps import ModelSteps, empty_branches, seeded
from xvoe.inference.score import nll_config
from xvoe.inference.smc import run_smc
from xvoe.inference.surprise import scene_and_proposal
from xvoe.models.nll import InferenceConfig
from xvoe.training.data import check_size

BATCH = 16
MARGINS = (30.0, 45.0, 60.0)


@torch.no_grad()
def trails(scorer, batch: dict, drawn, index: int, config: InferenceConfig, runs: int, seed: int) -> np.ndarray | None:
    """(runs,) trails of one video's full runs, or None where the head doubts an object."""
    frames, visible, occluder = (batch[name][index] for name in ("frames", "visible", "occluder"))
    scene, proposal, free = scene_and_proposal(scorer.vae, scorer.xpl, visible, occluder, drawn.video(index), config)
    if not free or float(proposal.p_exists) <= config.smc_pilot_skip_exists:
        return None
    full = out_of_sight(scene, proposal, frames, config)
    model = HiddenObjectModel(scene, config)
    versions = torch.arange(scene.versions, dtype=torch.float64)
    known = float(torch.logsumexp(empty_branches(model, frames).sum(1), 0))
    found = []
    for run in range(runs):
        generator = torch.Generator().manual_seed(seed * 1_000_003 + run)
        with seeded(generator):
            steps = ModelSteps(model, frames, full, widenings_of(config), {"exists": 1.0, "two": versions})
            made = run_smc(steps, config.particles, runs=scene.versions, threshold=config.resample_threshold,
                           generator=generator)
        found.append(known - float(torch.logsumexp(made.log_evidence, 0)))
    return np.array(found)


def report(hidden: np.ndarray, seen: np.ndarray) -> None:
    """The trails (videos, runs) of each kind, and what each margin of MARGINS would do."""
    summary = [f"hidden_videos={len(hidden)}"]
    if len(hidden):
        best = hidden.min(axis=1, keepdims=True)                  # the run that finds the object best
        missed = hidden[(hidden > 0) & (best < 0)]                # runs that trail where another leads
        largest = float(missed.max()) if missed.size else float("nan")
        print(f"object visible in no frame: {len(hidden)} videos, {hidden.size} runs; {int((best[:, 0] > 0).sum())} "
              f"videos with no run that leads (no object found); {missed.size} runs trail while another run of "
              f"their video leads, by at most {largest:.1f} nats")
        summary.append(f"largest_miss_trail={largest:.1f}")
        for margin in MARGINS:
            wrong = int(((hidden > margin) & (best < 0)).sum())
            print(f"  margin {margin:.0f}: {wrong} runs would end a video another run finds the object in")
            summary.append(f"wrong_stops_{margin:.0f}={wrong}")
    summary.append(f"seen_videos={len(seen)}")
    if len(seen):
        low = np.percentile(seen, [0, 1, 5, 50])
        print(f"every object seen: {len(seen)} videos, {seen.size} runs; trail smallest {low[0]:.1f}, 1st "
              f"percentile {low[1]:.1f}, 5th {low[2]:.1f}, median {low[3]:.1f} nats")
        for margin in MARGINS:
            print(f"  margin {margin:.0f}: ends {int((seen > margin).sum())} of {seen.size} first runs")
        summary.append(f"smallest_seen_trail={low[0]:.1f}")
    print(" ".join(summary))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a shipped model's name, a run directory or checkpoint")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--runs", type=int, default=6, help="full runs a video (default 6)")
    parser.add_argument("--first", type=int, default=0, help="the first video (default 0)")
    parser.add_argument("--last", type=int, help="the video after the last (default: the split's end)")
    parser.add_argument("--cap", type=int, help="at most this many sure videos")
    parser.add_argument("--truth", choices=("hidden", "seen", "both"), default="both",
                        help="the videos of one ground truth only (default both)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scorer = xvoe.load_model(args.model)
    config = nll_config(scorer.nll or InferenceConfig())
    found = {"hidden": [], "seen": []}
    with xvoe.open_dataset(args.data) as file:
        check_size(file, scorer.image_size, f"the model {scorer.name}")
        last = file["rgbd"].shape[0] if args.last is None else min(args.last, file["rgbd"].shape[0])
        for start in tqdm(range(args.first, last, BATCH), desc="sure runs", unit="batch"):
            if args.cap is not None and sum(map(len, found.values())) >= args.cap:
                break
            stop = min(last, start + BATCH)
            truths = [ground_truth(file, index) for index in range(start, stop)]
            if args.truth != "both" and args.truth not in truths:
                continue                     # nothing to run here: its videos need not be encoded
            batch = encode_videos(scorer, file, start, stop, None)
            drawn = draw_scene(scorer.vae, scorer.xpl, batch["mean"], batch["visible"], batch["background"],
                               batch["occluder"])
            for index, truth in enumerate(truths):
                if args.truth not in ("both", truth):
                    continue
                trail = trails(scorer, batch, drawn, index, config, args.runs, args.seed)
                if trail is not None:
                    found[truth].append(trail)
    print(f"model {args.model}, {args.data} videos {args.first}-{last}: {args.runs} full runs of "
          f"{config.particles} particles each where the head is sure, seed {args.seed}")
    report(*(np.array(found[truth]).reshape(-1, args.runs) for truth in ("hidden", "seen")))


if __name__ == "__main__":
    main()
