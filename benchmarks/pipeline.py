"""The default pipeline, measured: wall time per stage, peak memory, scoring throughput,
and the accuracy goals of DESIGN section 7 on a fresh test set.

    python benchmarks/pipeline.py --out runs/bench [--train-videos 10000] [--pairs 200]
                                  [--fresh-pairs 1000] [--models xpl,random]

Runs `xvoe pipeline` (skipping stages a previous run finished), then scores a fresh test set
(a seed neither training nor the pipeline's test split used) and checks the goals:
predictive (S1) >= 95% in every scenario, explicative (S3) >= 90% for collision and blocking,
hypothetical (S2) within 50 +- 15%, holistic AUC >= 0.85 per scenario.
"""
from __future__ import annotations

import argparse
import csv
import resource
import time
from pathlib import Path

from xvoe.apps.pipeline import PipelineConfig, run_pipeline
from xvoe.benchmark.generate import GenerateConfig, generate
from xvoe.evaluation.metrics import comparative, holistic, read_scores
from xvoe.evaluation.score import score_split
from xvoe.training.recipes import recipe

FRESH_SEED = 12345


def peak_memory_gib() -> float:
    """Largest resident set of this process or any finished child, GiB (Linux: KiB units)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 2**20


def goals(scores: dict) -> list[str]:
    """One line per goal: the measured value, the target and whether it is met."""
    lines = []
    compared = comparative(scores, rounds=200)
    for (scenario, setting), estimate in compared.items():
        value = 100 * estimate.value
        if setting == "S1":
            target, met = ">= 95", value >= 95
        elif setting == "S3" and scenario in ("collision", "blocking"):
            target, met = ">= 90", value >= 90
        elif setting == "S2":
            target, met = "50 +- 15", abs(value - 50) <= 15
        else:
            target, met = "(none)", True
        lines.append(f"comparative {scenario} {setting}: {value:.1f} (target {target}) {'ok' if met else 'MISSED'}")
    for scenario, estimate in holistic(scores, rounds=200).items():
        met = estimate.value >= 0.85
        lines.append(f"holistic {scenario}: {estimate.value:.3f} (target >= 0.85) {'ok' if met else 'MISSED'}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--recipe", default="cpu")
    parser.add_argument("--train-videos", type=int, help="default: the recipe's")
    parser.add_argument("--pairs", type=int, default=200)
    parser.add_argument("--fresh-pairs", type=int, default=1000)
    parser.add_argument("--models", default="xpl,random")
    args = parser.parse_args()
    models = tuple(args.models.split(","))
    start = time.monotonic()
    report = run_pipeline(PipelineConfig(args.out, args.recipe, args.train_videos, args.pairs, models, progress=False))
    wall = time.monotonic() - start
    run_dir = Path(args.out)
    print(f"pipeline: {wall / 60:.1f} min wall this run, peak memory {peak_memory_gib():.2f} GiB, report {report}")
    for mark in sorted((run_dir / ".done").iterdir()):
        print(f"  {mark.name}: {mark.read_text().strip()}")

    fresh = run_dir / "data" / "fresh-test.h5"
    if not fresh.exists():
        size = recipe(args.recipe).perception.image_size
        generate(GenerateConfig("test", pairs=args.fresh_pairs, size=size, seed=FRESH_SEED), fresh, workers=2,
                 progress=False)
    for model in (m for m in models if m != "random"):
        out = run_dir / "scores" / f"fresh-{model}.csv"
        start = time.monotonic()
        score_split(str(run_dir / f"{model}.pt"), str(fresh), str(out), overwrite=True, progress=False)
        seconds = time.monotonic() - start
        videos = sum(1 for _ in csv.reader(open(out))) - 1
        print(f"{model}: scoring {videos / seconds:.1f} videos/s on the fresh test set ({videos} videos)")
        for line in goals(read_scores(out)):
            print(f"  {line}")
    print(f"peak_memory_gib={peak_memory_gib():.2f} pipeline_minutes={wall / 60:.1f}")


if __name__ == "__main__":
    main()
