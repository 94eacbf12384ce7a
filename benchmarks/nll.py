"""The NLL surprise, measured: its scoring speed, the ESS, the hidden-object posterior, its
repeatability between seeds, and its accuracy against the MSE score on the same pairs.

    python benchmarks/nll.py --model NAME_OR_RUN --data test.h5 [--particles N] [--pairs N] [--threads 2]
                             [--seeds 0,1] [--rows rows.csv] [--nll-set FIELD=VALUE ...]

`--nll-set` changes a field of the model's NLL settings (xvoe.models.nll.InferenceConfig: method,
pixel_sigma, motion_sigma, smc_pilot, refine_steps, proposal_widening, ...), as xvoe score's.

Scores the first N pairs of every S1 and S3 setting and of blocking S2 with both surprise
definitions, each video encoded once (as `xvoe score --surprise both` does), the NLL once per
seed.
(a) videos_per_s: NLL scoring throughput of the first seed, encoding included, MSE excluded
    (goal >= 8 at 64 particles on 2 cores).
(b) ESS: the median effective sample size among the particles that hold an object, on the
    videos whose ground truth holds an object visible in no frame (goal >= 16 of 64).
(c) p_hidden_hidden: of those videos, the share with p_hidden > 0.5; (d) p_hidden_seen: of the
    videos in which every object is seen at some frame, the share with p_hidden < 0.5 (goal of
    both >= 0.95).
(e) repeatability: |NLL(seed 0) - NLL(seed 1)| per video, median and 99th percentile (goal
    <= 0.5 and <= 5 nats), with two seeds or more.
(f) comparative accuracy of the NLL against the MSE score in every S1 and S3 setting (goal
    >= 99%), and the holistic AUC of the NLL excess per scenario (goal >= 0.9).
Last line: videos_per_s=N.N holding_ess=N.N p_hidden_hidden=0.NN p_hidden_seen=0.NN repeat_median=N.NN
repeat_p99=N.NN min_comparative=N.N min_excess_auc=N.NN
"""
from __future__ import annotations

import argparse
import csv
import time
from collections.abc import Callable

import numpy as np
import torch
from tqdm.auto import tqdm

import xvoe
from xvoe import allocator
from xvoe.evaluation.explanation_quality import ground_truth
from xvoe.evaluation.scorer import encode_videos
from xvoe.evaluation.surprise import mse_surprise
from xvoe.inference.score import nll_config, reference_nll
from xvoe.inference.surprise import nll_surprise
from xvoe.models.nll import InferenceConfig
from xvoe.scenes import store
from xvoe.scenes.scenarios import SCENARIOS, TEST_SETTINGS
from xvoe.training.data import check_size

SETTINGS = [(scenario, setting) for setting in ("S1", "S3") for scenario in SCENARIOS
            if (scenario, setting) in TEST_SETTINGS] + [("blocking", "S2")]
BATCH = 16


def chosen_ranges(file, pairs: int) -> list[tuple[int, int]]:
    """[start, stop) of the first `pairs` pairs of each benchmarked setting (pairs are stored
    setting by setting, member 0 then 1: docs/benchmark.md)."""
    scenario, setting = store.strings(file, "scenario"), store.strings(file, "setting")
    ranges = []
    for name, kind in SETTINGS:
        where = np.flatnonzero((scenario == name) & (setting == kind))
        if len(where) == 0:
            raise xvoe.XvoeError(f"{file.filename} holds no {name} {kind} pairs; give a whole test split")
        ranges.append((int(where[0]), int(where[0]) + min(len(where), 2 * pairs)))
    return ranges


@torch.no_grad()
def score_range(scorer, file, start: int, stop: int, config: InferenceConfig,
                seeds: list[int]) -> tuple[list[dict], float, float]:
    """Both surprises of videos [start, stop), the NLL once per seed; the seconds spent on the
    NLL of the first seed (encoding included) and on the MSE score."""
    began = time.perf_counter()
    batch = encode_videos(scorer, file, start, stop)
    encoded = time.perf_counter()
    rows, first_seed = [], 0.0
    for i in range(stop - start):
        video = [batch[k][i] for k in ("frames", "mean", "visible", "background", "occluder")]
        row = {"index": start + i}
        for n, seed in enumerate(seeds):
            tick, cpu = time.perf_counter(), time.process_time()
            found = nll_surprise(scorer.vae, scorer.xpl, *video, config, seed=seed)
            first_seed += time.perf_counter() - tick if n == 0 else 0.0
            row["cpu_seconds"] = row.get("cpu_seconds", time.process_time() - cpu)
            if n == 0:
                row |= {"nll": found.nll, "ess": found.ess, "holding_ess": found.holding_ess,
                        "p_hidden": found.p_hidden, "particles": getattr(found.estimate, "particles", ""),
                        "slot": found.hidden_slot}
            row[f"nll_{n}"] = found.nll
        rows.append(row)
    nll_done = time.perf_counter()
    surprise = mse_surprise(scorer.vae, scorer.xpl, batch["frames"], batch["mean"], batch["visible"],
                            batch["background"], batch["occluder"])
    size = batch["frames"].shape[-1]
    reference = reference_nll(surprise.s_rec.numpy(), 4 * size * size, config.pixel_sigma)
    for row, value, ref in zip(rows, surprise.per_frame.sum(dim=1).tolist(), reference):
        row["score"], row["nll_excess"] = value, row["nll"] - float(ref)
    return rows, first_seed + (encoded - began), time.perf_counter() - nll_done + (encoded - began)


def label(rows: list[dict], file) -> dict[str, np.ndarray]:
    """The scored rows as a scores table (the columns xvoe.read_scores reads)."""
    index = np.array([r["index"] for r in rows])
    table = {"index": index, "scenario": store.strings(file, "scenario")[index],
             "setting": store.strings(file, "setting")[index]}
    for name in ("pair", "member", "possible"):
        table[name] = file[name][:][index]
    for name in ("score", "nll", "ess", "holding_ess", "p_hidden", "truth", "nll_excess", "cpu_seconds", "particles",
                 "slot"):
        table[name] = np.array([r[name] for r in rows])
    seeds = sum(1 for name in rows[0] if name.startswith("nll_") and name[4:].isdigit())
    table["repeat"] = (np.abs(np.array([r["nll_1"] - r["nll_0"] for r in rows])) if seeds > 1
                       else np.full(len(rows), np.nan))
    return table


def share(values: np.ndarray) -> float:
    return float(values.mean()) if len(values) else float("nan")


def arguments(description: str) -> argparse.ArgumentParser:
    """The options every NLL benchmark takes: the model, the split, the rows' CSV and --nll-set."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--model", required=True, help="a shipped model's name (xpl), a run directory or checkpoint")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--rows", help="also write each video's figures to this CSV")
    parser.add_argument("--nll-set", action="append", default=[], metavar="FIELD=VALUE",
                        help="change a field of the NLL's settings (inference.InferenceConfig), as xvoe score's")
    return parser


def run_or_exit(run: Callable[[argparse.Namespace], None], args: argparse.Namespace, name: str) -> None:
    """`run(args)`, a project error its one line on stderr and exit 2."""
    try:
        run(args)
    except xvoe.XvoeError as error:
        raise SystemExit(f"{name}: error: {error}") from None


def main() -> None:
    parser = arguments(__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, help="particles per video (default: the model's NLL settings)")
    parser.add_argument("--pairs", type=int, default=1_000_000, help="pairs per setting (default: all)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--seeds", default="0,1", help="comma-separated seeds; each video is scored with each "
                                                        "(default 0,1: repeatability)")
    run_or_exit(run, parser.parse_args(), "nll.py")


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    seeds = [int(seed) for seed in args.seeds.split(",")]
    scorer = xvoe.load_model(args.model)
    if scorer.xpl is None or not scorer.xpl.config.use_reasoning:
        raise xvoe.XvoeError(f"the NLL surprise needs an XPL model with reasoning; {scorer.name} has none")
    config = nll_config(scorer.nll or InferenceConfig(), args.particles, xvoe.nll_settings(args.nll_set))
    rows, nll_seconds, mse_seconds = [], 0.0, 0.0
    with xvoe.open_dataset(args.data) as file:
        check_size(file, scorer.image_size, f"the model {scorer.name}")
        batches = [(a, min(stop, a + BATCH)) for start, stop in chosen_ranges(file, args.pairs)
                   for a in range(start, stop, BATCH)]
        for start, stop in tqdm(batches, desc="nll benchmark", unit="batch"):
            scored, nll_time, mse_time = score_range(scorer, file, start, stop, config, seeds)
            for row in scored:
                row["truth"] = ground_truth(file, row["index"])
            rows += scored
            nll_seconds, mse_seconds = nll_seconds + nll_time, mse_seconds + mse_time
        table = label(rows, file)
    if args.rows:
        with open(args.rows, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    report(table, args, config, nll_seconds, mse_seconds)


def report(table: dict[str, np.ndarray], args: argparse.Namespace, config: InferenceConfig, nll_seconds: float,
           mse_seconds: float) -> None:
    """Print the figures; the last line is the summary."""
    videos = len(table["index"])
    speed = videos / nll_seconds
    print(f"model {args.model}, {args.data}: {videos} videos ({args.pairs if args.pairs < 1_000_000 else 'all'} "
          f"pairs per setting), seeds {args.seeds}, {args.threads} thread(s), {config}")
    print(f"NLL scoring: {speed:.2f} videos/s (first seed, encoding included, {nll_seconds:.0f} s); "
          f"MSE scoring: {videos / mse_seconds:.1f} videos/s (encoding included)")
    cpu = table["cpu_seconds"]      # the process's CPU time: less sensitive than the clock to other jobs
    print(f"NLL CPU time per video (first seed, encoding excluded, all threads): mean {cpu.mean():.3f} s, "
          f"{1 / cpu.mean():.2f} videos per CPU-second; on the videos with an object visible in no frame "
          f"{cpu[table['truth'] == 'hidden'].mean():.3f} s")
    hidden, seen = table["truth"] == "hidden", table["truth"] == "seen"
    free = table["slot"] >= 0       # a video with no slot free for a hidden object runs no SMC of one
    ended = free & (table["particles"] < config.particles)     # the kept run is the pilot's: the video ended there
    for name, rows in (("ended at the pilot", ended), ("took the full run", free & ~ended),
                       ("had no free slot", ~free)):
        if rows.any():
            print(f"  {int(rows.sum())} videos {name} ({int((rows & hidden).sum())} with an object visible in no "
                  f"frame): mean {cpu[rows].mean():.3f} s, {cpu[rows].sum() / cpu.sum():.0%} of the CPU time")
    holding = table["holding_ess"][hidden]
    holding_ess = float(np.median(holding)) if len(holding) else float("nan")
    if hidden.any():
        print(f"ESS among the particles that hold an object, on the {int(hidden.sum())} videos with an object "
              f"visible in no frame: median {holding_ess:.1f}, 10th percentile {np.percentile(holding, 10):.1f}, "
              f"lowest {holding.min():.1f}, of {int(table['particles'][hidden].max())} particles (where the existence "
              f"head is sure, runs pooled; goal: median >= 16)")
    p_hidden_hidden = share(table["p_hidden"][hidden] > 0.5)
    p_hidden_seen = share(table["p_hidden"][seen] < 0.5)
    print(f"p_hidden > 0.5 on {int((table['p_hidden'][hidden] > 0.5).sum())} of {int(hidden.sum())} videos with an "
          f"object visible in no frame: {p_hidden_hidden:.2f} (goal >= 0.95)")
    print(f"p_hidden < 0.5 on {int((table['p_hidden'][seen] < 0.5).sum())} of {int(seen.sum())} videos in which "
          f"every object is seen at some frame: {p_hidden_seen:.2f} (goal >= 0.95)")
    for possible, name in ((True, "possible"), (False, "impossible")):
        group = seen & (table["possible"] == possible)
        print(f"  of them {name}: p_hidden < 0.5 on {int((table['p_hidden'][group] < 0.5).sum())} of {int(group.sum())}"
              + ("" if possible else " (a hidden object is the model's explanation of an impossible event)"))
    repeat = table["repeat"]
    repeat_median = float(np.median(repeat))
    repeat_p99 = float(np.percentile(repeat, 99))
    if np.isfinite(repeat).all():
        print(f"|NLL(seed a) - NLL(seed b)|: median {repeat_median:.3f}, 99th percentile {repeat_p99:.2f}, "
              f"largest {repeat.max():.2f} nats (goal <= 0.5 and <= 5); on the videos with an object visible "
              f"in no frame: median {np.median(repeat[hidden]) if hidden.any() else float('nan'):.2f}, "
              f"largest {repeat[hidden].max() if hidden.any() else float('nan'):.2f}")
    print("comparative accuracy on the same pairs, MSE score -> NLL (goal: NLL >= 99% in every S1 and S3 setting):")
    mse, nll = xvoe.comparative(table, "score", rounds=200), xvoe.comparative(table, "nll", rounds=200)
    lowest = 1.0
    for key in (k for k in mse if k[1] != "S2"):
        lowest = min(lowest, nll[key].value)
        print(f"  {key[0]} {key[1]}: {100 * mse[key].value:.1f}% -> {100 * nll[key].value:.1f}% "
              f"(NLL 95% interval {100 * nll[key].low:.0f}-{100 * nll[key].high:.0f})")
    print("holistic AUC of the NLL excess per scenario (goal >= 0.9):")
    aucs = xvoe.holistic(table, "nll_excess", rounds=200)
    for scenario, estimate in aucs.items():
        print(f"  {scenario}: {estimate.value:.3f} (95% interval {estimate.low:.2f}-{estimate.high:.2f})")
    lowest_auc = min(e.value for e in aucs.values())
    print(f"videos_per_s={speed:.1f} holding_ess={holding_ess:.1f} p_hidden_hidden={p_hidden_hidden:.2f} "
          f"p_hidden_seen={p_hidden_seen:.2f} repeat_median={repeat_median:.2f} repeat_p99={repeat_p99:.2f} "
          f"min_comparative={100 * lowest:.1f} min_excess_auc={lowest_auc:.2f}")


if __name__ == "__main__":
    allocator.tune()        # timed as the command line runs: with its malloc settings
    main()
