"""How far the NLL's hidden-object branch trails where the existence head doubts an object, at
each pilot size: what decides how small the SMC's pilot may be.

    python benchmarks/nll_pilot.py --model xpl --data val.h5 [--sizes 4,8,16,64] [--seed 0] [--threads 1]

For every video of the split with a slot free for a hidden object and an existence probability
at most `smc_pilot_skip_exists` (the videos that take a pilot, and those under `smc_object_floor`,
which take none on the strength of what this measures), each explanation of what was seen
is run by SMC at every size (a pilot from Transformer 2's mean, the full run from that mean moved
out of sight, as `hidden_runs` runs them); its trail is log p(x, no object) summed over the
explanations (exact) less the run's log p^(x, object, explanation). A pilot of size n stops an explanation where its
trail exceeds `smc_pilot_margin`; the NLL then moves by less than exp(-margin). Printed: each
size's trail percentiles, and how many explanations a pilot of each size stops that the full
run would not (those whose full-run trail is within the margin).
Last line: smallest_trail_SIZE=N.N ... wrong_stops_SIZE=N ...
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from tqdm.auto import tqdm

import xvoe
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


@torch.no_grad()
def trails(scorer, batch: dict, drawn, index: int, config: InferenceConfig, sizes: list[int],
           seed: int) -> np.ndarray | None:
    """(sizes, V) trails of one video's explanations, or None where it takes no pilot."""
    frames, visible, occluder = (batch[name][index] for name in ("frames", "visible", "occluder"))
    scene, proposal, free = scene_and_proposal(scorer.vae, scorer.xpl, visible, occluder, drawn.video(index), config)
    if not free or float(proposal.head) > config.smc_pilot_skip_exists:
        return None
    full = out_of_sight(scene, proposal, frames, config)
    model, generator = HiddenObjectModel(scene, config), torch.Generator().manual_seed(seed)
    versions = torch.arange(scene.versions, dtype=torch.float64)
    with seeded(generator):
        known = float(torch.logsumexp(empty_branches(model, frames).sum(1), 0))
        found = []
        for size in sizes:
            drawn_from = full if size == sizes[-1] else proposal     # as `hidden_runs` draws
            steps = ModelSteps(model, frames, drawn_from, widenings_of(config), {"exists": 1.0, "two": versions})
            run = run_smc(steps, size, runs=scene.versions, threshold=config.resample_threshold, generator=generator)
            found.append(known - run.log_evidence.numpy())
    return np.stack(found)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a shipped model's name, a run directory or checkpoint")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--sizes", default="4,8,16,64", help="pilot sizes, the last the full run (default 4,8,16,64)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    sizes = [int(size) for size in args.sizes.split(",")]
    scorer = xvoe.load_model(args.model)
    config = nll_config(scorer.nll or InferenceConfig())
    found = []
    with xvoe.open_dataset(args.data) as file:
        check_size(file, scorer.image_size, f"the model {scorer.name}")
        count = file["rgbd"].shape[0]
        for start in tqdm(range(0, count, BATCH), desc="pilot trails", unit="batch"):
            batch = encode_videos(scorer, file, start, min(count, start + BATCH), None)
            drawn = draw_scene(scorer.vae, scorer.xpl, batch["mean"], batch["visible"], batch["background"],
                               batch["occluder"])
            for index in range(len(batch["mean"])):
                trail = trails(scorer, batch, drawn, index, config, sizes, args.seed)
                if trail is not None:
                    found.append(trail)
    table = np.concatenate(found, axis=1)                  # (sizes, explanations)
    margin, full = config.smc_pilot_margin, table[-1]
    print(f"model {args.model}, {args.data}: {len(found)} videos take a pilot ({table.shape[1]} explanations), "
          f"seed {args.seed}, margin {margin} nats")
    summary = []
    for size, row in zip(sizes, table):
        wrong = int(((row > margin) & (full <= margin)).sum())
        low = np.percentile(row, [0, 1, 5, 50])
        print(f"{size} particles: trail smallest {low[0]:.1f}, 1st percentile {low[1]:.1f}, 5th {low[2]:.1f}, "
              f"median {low[3]:.1f} nats; stops {int((row > margin).sum())}, of them {wrong} the full run would not")
        summary += [f"smallest_trail_{size}={low[0]:.1f}", f"wrong_stops_{size}={wrong}"]
    print(" ".join(summary))


if __name__ == "__main__":
    main()
