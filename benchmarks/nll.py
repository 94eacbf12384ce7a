"""The NLL surprise, measured: its scoring speed, the ESS, the hidden-object posterior, and its
comparative accuracy against the MSE score on the same pairs.

    python benchmarks/nll.py --model NAME_OR_RUN --data test.h5 [--particles 64] [--pairs N] [--threads 2]
                             [--motion-sigma S] [--pixel-sigma S] [--refine-steps N] [--proposal-widening F]
                             [--independent-guide]

Scores the first N pairs of every S1 and S3 setting and of blocking S2 with both surprise
definitions, each video encoded once (as `xvoe score --surprise both` does).
(a) videos_per_s: NLL scoring throughput, encoding included, MSE excluded (goal >= 5 at 64
    particles on 2 cores).
(b) median_ess: the median effective sample size of the importance weights (and, apart, on
    the hidden-cube videos of (c), where it is far lower).
(c) p_hidden_hidden: of the blocking S2 member-0 videos whose ground truth holds an object
    visible in no frame (the saved states' `visible` column), the share with p_hidden > 0.5.
(d) p_hidden_seen: of the scored videos in which every object is seen at some frame, the share
    with p_hidden < 0.5. Goal of (c) and (d): >= 0.8 each.
(e) comparative accuracy of the NLL against the MSE score in every S1 and S3 setting (goal:
    the NLL at least the MSE's).
Last line: videos_per_s=N.N median_ess=N.N p_hidden_hidden=0.NN p_hidden_seen=0.NN
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import pyro
import torch
from tqdm.auto import tqdm

from inference.model import InferenceConfig
from inference.score import xpl_nll
from xvoe.benchmark import store
from xvoe.errors import XvoeError
from xvoe.evaluation.metrics import comparative
from xvoe.evaluation.score import encode_videos, load_model
from xvoe.evaluation.surprise import mse_surprise
from xvoe.training.data import check_size

SETTINGS = [(scenario, setting) for setting in ("S1", "S3")
            for scenario in ("collision", "blocking", "permanence", "continuity")
            if (scenario, setting) != ("permanence", "S3")] + [("blocking", "S2")]
BATCH = 16


def chosen_ranges(file, pairs: int) -> list[tuple[int, int]]:
    """[start, stop) of the first `pairs` pairs of each benchmarked setting (pairs are stored
    setting by setting, member 0 then 1: docs/benchmark.md)."""
    scenario, setting = store.strings(file, "scenario"), store.strings(file, "setting")
    ranges = []
    for name, kind in SETTINGS:
        where = np.flatnonzero((scenario == name) & (setting == kind))
        if len(where) == 0:
            raise XvoeError(f"{file.filename} holds no {name} {kind} pairs; give a whole test split")
        ranges.append((int(where[0]), int(where[0]) + min(len(where), 2 * pairs)))
    return ranges


def ground_truth(file, index: int, names: list[str], columns: list[str]) -> str:
    """"hidden": an object visible in no frame; "seen": every object seen at some frame."""
    visible = file["states"][index][:, :, columns.index("visible")].max(axis=0)
    objects = [k for k, kind in enumerate(file["kind"][index]) if names[kind] != "none"]
    return "hidden" if any(visible[k] == 0 for k in objects) else "seen"


@torch.no_grad()
def score_range(scorer, file, start: int, stop: int, config: InferenceConfig) -> tuple[list[dict], float, float]:
    """Both surprises of videos [start, stop); the seconds spent on the NLL (encoding included)
    and on the MSE score."""
    began = time.perf_counter()
    batch = encode_videos(scorer, file, start, stop)
    encoded = time.perf_counter()
    rows = [{"index": start + i, "nll": nll, "ess": ess, "p_hidden": p_hidden}
            for i, (nll, ess, p_hidden) in enumerate(xpl_nll(scorer, batch, config))]
    nll_done = time.perf_counter()
    mse = mse_surprise(scorer.vae, scorer.xpl, batch["frames"], batch["mean"], batch["visible"], batch["background"],
                       batch["occluder"]).per_frame.sum(dim=1)
    for row, value in zip(rows, mse.tolist()):
        row["score"] = value
    return rows, nll_done - began, time.perf_counter() - nll_done + (encoded - began)


def label(rows: list[dict], file) -> dict[str, np.ndarray]:
    """The scored rows as a scores table (the columns xvoe.read_scores reads)."""
    index = np.array([r["index"] for r in rows])
    table = {"index": index, "scenario": store.strings(file, "scenario")[index],
             "setting": store.strings(file, "setting")[index]}
    for name in ("pair", "member", "possible"):
        table[name] = file[name][:][index]
    for name in ("score", "nll", "ess", "p_hidden", "truth"):
        table[name] = np.array([r[name] for r in rows])
    return table


def share(values: np.ndarray) -> float:
    return float(values.mean()) if len(values) else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a shipped model's name (xpl), a run directory or checkpoint")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--particles", type=int, default=64, help="importance samples per video (default 64)")
    parser.add_argument("--pairs", type=int, default=1_000_000, help="pairs per setting (default: all)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the importance samples")
    parser.add_argument("--motion-sigma", type=float, default=InferenceConfig.motion_sigma,
                        help="standard deviation of the seen objects' latents around the dynamics "
                             f"(default {InferenceConfig.motion_sigma})")
    parser.add_argument("--pixel-sigma", type=float, default=InferenceConfig.pixel_sigma,
                        help=f"standard deviation of the pixel likelihood (default {InferenceConfig.pixel_sigma})")
    parser.add_argument("--refine-steps", type=int, default=InferenceConfig.refine_steps,
                        help="gradient steps that move the proposal's mean out of sight "
                             f"(default {InferenceConfig.refine_steps})")
    parser.add_argument("--refine-rate", type=float, default=InferenceConfig.refine_rate,
                        help=f"their learning rate (default {InferenceConfig.refine_rate})")
    parser.add_argument("--proposal-widening", type=float, default=InferenceConfig.proposal_widening,
                        help="factor on Transformer 2's scales before they are fused with the latent prior and "
                             f"the dynamics' step (default {InferenceConfig.proposal_widening})")
    parser.add_argument("--independent-guide", action="store_true",
                        help="draw the hidden trajectory frame by frame from Transformer 2 alone (the guide "
                             "before it was fused with the dynamics' step), for comparison")
    args = parser.parse_args()
    try:
        run(args)
    except XvoeError as error:
        raise SystemExit(f"nll.py: error: {error}") from None


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    pyro.set_rng_seed(args.seed)
    scorer = load_model(args.model)
    if scorer.xpl is None or not scorer.xpl.config.use_reasoning:
        raise XvoeError(f"the NLL surprise needs an XPL model with reasoning; {scorer.name} has none")
    config = InferenceConfig(particles=args.particles, motion_sigma=args.motion_sigma, pixel_sigma=args.pixel_sigma,
                             refine_steps=args.refine_steps,
                             refine_rate=args.refine_rate, proposal_widening=args.proposal_widening,
                             guide_follows_dynamics=not args.independent_guide)
    rows, nll_seconds, mse_seconds = [], 0.0, 0.0
    with store.open_dataset(args.data) as file:
        check_size(file, scorer.image_size, f"the model {scorer.name}")
        names, columns = list(file.attrs["kind_names"]), list(file["states"].attrs["state_columns"])
        batches = [(a, min(stop, a + BATCH)) for start, stop in chosen_ranges(file, args.pairs)
                   for a in range(start, stop, BATCH)]
        for start, stop in tqdm(batches, desc="nll benchmark", unit="batch"):
            scored, nll_time, mse_time = score_range(scorer, file, start, stop, config)
            for row in scored:
                row["truth"] = ground_truth(file, row["index"], names, columns)
            rows += scored
            nll_seconds, mse_seconds = nll_seconds + nll_time, mse_seconds + mse_time
        table = label(rows, file)
    report(table, args, nll_seconds, mse_seconds)


def report(table: dict[str, np.ndarray], args: argparse.Namespace, nll_seconds: float, mse_seconds: float) -> None:
    """Print the figures; the last line is the summary."""
    videos = len(table["index"])
    speed, median_ess = videos / nll_seconds, float(np.median(table["ess"]))
    print(f"model {args.model}, {args.data}: {videos} videos ({args.pairs if args.pairs < 1_000_000 else 'all'} "
          f"pairs per setting), {args.particles} particles, {args.threads} thread(s), "
          f"{'independent' if args.independent_guide else 'dynamics-fused'} guide, motion sigma {args.motion_sigma}, "
          f"pixel sigma {args.pixel_sigma}, "
          f"{args.refine_steps} steps out of sight at rate {args.refine_rate}, proposal widening "
          f"{args.proposal_widening}")
    print(f"NLL scoring: {speed:.2f} videos/s (encoding included, {nll_seconds:.0f} s); "
          f"MSE scoring: {videos / mse_seconds:.1f} videos/s (encoding included)")
    print(f"ESS: median {median_ess:.1f}, 10th percentile {np.percentile(table['ess'], 10):.1f} "
          f"of {args.particles}")
    blocking_s2 = (table["scenario"] == "blocking") & (table["setting"] == "S2")
    hidden = blocking_s2 & (table["member"] == 0) & (table["truth"] == "hidden")
    seen = table["truth"] == "seen"
    if hidden.any():    # there the particles holding an object carry the weight, and few of them do
        print(f"ESS on the {int(hidden.sum())} blocking S2 member-0 videos with an object visible in no frame: "
              f"median {np.median(table['ess'][hidden]):.1f} of {args.particles}")
    p_hidden_hidden = share(table["p_hidden"][hidden] > 0.5)
    p_hidden_seen = share(table["p_hidden"][seen] < 0.5)
    print(f"p_hidden > 0.5 on {int((table['p_hidden'][hidden] > 0.5).sum())} of {int(hidden.sum())} blocking S2 "
          f"member-0 videos with an object visible in no frame: {p_hidden_hidden:.2f} (goal >= 0.80)")
    print(f"p_hidden < 0.5 on {int((table['p_hidden'][seen] < 0.5).sum())} of {int(seen.sum())} videos in which "
          f"every object is seen at some frame: {p_hidden_seen:.2f} (goal >= 0.80)")
    for scenario, setting in SETTINGS:
        group = seen & (table["scenario"] == scenario) & (table["setting"] == setting)
        if group.any():
            print(f"  {scenario} {setting}: p_hidden < 0.5 on {share(table['p_hidden'][group] < 0.5):.2f} "
                  f"of {int(group.sum())}; median p_hidden {np.median(table['p_hidden'][group]):.2f}")
    print("comparative accuracy on the same pairs, MSE score -> NLL (goal: NLL >= MSE in every S1 and S3 setting):")
    mse, nll = comparative(table, "score", rounds=200), comparative(table, "nll", rounds=200)
    for key in (k for k in mse if k[1] != "S2"):
        verdict = "ok" if nll[key].value >= mse[key].value else "NLL below MSE"
        print(f"  {key[0]} {key[1]}: {100 * mse[key].value:.1f}% -> {100 * nll[key].value:.1f}% "
              f"(NLL 95% interval {100 * nll[key].low:.0f}-{100 * nll[key].high:.0f}) {verdict}")
    print(f"videos_per_s={speed:.1f} median_ess={median_ess:.1f} p_hidden_hidden={p_hidden_hidden:.2f} "
          f"p_hidden_seen={p_hidden_seen:.2f}")


if __name__ == "__main__":
    main()
