"""A recipe over training seeds: the README's results table, from one command.

    python benchmarks/seeds.py --runs runs/s0,runs/s1,runs/s2 --data report.h5 --out seeds/ [--shipped xpl]
                               [--surprise mse] [--column score|paper_score] [--hidden-pairs 100]

Scores the report split with each run's model (and the shipped one, beside them), then prints
one markdown table: comparative accuracy per setting as the mean over the runs with its range
(lowest, highest), each run's own value, and the shipped model's; the S3 - S2 gap per scenario
(S2 has no goal of its own: docs/design.md, "Metrics"); holistic AUC; and hidden_iou per model
(xvoe.evaluation.explanation_quality). The report split must come from a seed nothing was
chosen on (docs/design.md, "Recipes, choosing and shipping"). Scores already in --out are
reused, so that a model added later costs only its own scoring.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

import xvoe
from xvoe.evaluation.disagreements import VERDICTS
from xvoe.evaluation.explanation_quality import hidden_explanations, pick
from xvoe.training.stages import XPL


def scored(model: str, data: str, out: Path, surprise: str) -> dict:
    """The model's scores of the split (read back if --out already holds them)."""
    path = out / f"{Path(model).name or model}.csv"
    if not path.exists():
        xvoe.score(model, data, path, surprise=surprise, progress=False)
    return xvoe.read_scores(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", required=True, help="comma-separated run directories, one per training seed")
    parser.add_argument("--data", required=True, help="a report split (a seed nothing was chosen on)")
    parser.add_argument("--out", required=True, help="where the scores go")
    parser.add_argument("--shipped", default=XPL, help="the shipped model to show beside ('' for none)")
    parser.add_argument("--surprise", default="mse", choices=("mse", "both"))
    parser.add_argument("--hidden-pairs", type=int, default=100, help="blocking S2 videos for hidden_iou (0: none)")
    parser.add_argument("--column", default="score", choices=VERDICTS,
                        help="the default verdict (score) or the paper's score (paper_score)")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    runs = [r for r in args.runs.split(",") if r]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    models = runs + ([args.shipped] if args.shipped else [])
    column = args.column
    rows = {}
    for model in models:
        found = xvoe.metric_rows(scored(model, args.data, out, args.surprise), model, (column,))
        rows[model] = {(r["metric"], r["scenario"], r["setting"]): 100 * r["value"] for r in found}
    names = [Path(r).name for r in runs]
    print(f"Comparative accuracy (%) on {args.data}, {len(runs)} training seeds: mean [lowest, highest]\n")
    shipped_head = f" | shipped {args.shipped} |" if args.shipped else " |"
    print("| setting | mean [range] | " + " | ".join(names) + shipped_head)
    print("|---|---|" + "---|" * (len(names) + bool(args.shipped)))

    def line(label: str, values: list[float], shipped: float | None) -> None:
        cells = " | ".join(f"{v:.1f}" for v in values)
        tail = f" | {shipped:.1f}" if shipped is not None else ""
        print(f"| {label} | {np.mean(values):.1f} [{min(values):.1f}, {max(values):.1f}] | {cells}{tail} |")

    shipped_rows = rows.get(args.shipped) if args.shipped else None
    for scenario, setting in xvoe.TEST_SETTINGS:
        key = ("comparative", scenario, setting)
        line(f"{scenario} {setting}", [rows[r][key] for r in runs], shipped_rows[key] if shipped_rows else None)
    def gap(found: dict, scenario: str) -> float:
        return found[("comparative", scenario, "S3")] - found[("comparative", scenario, "S2")]

    for scenario in (s for s in xvoe.SCENARIOS if {(s, "S2"), (s, "S3")} <= set(xvoe.TEST_SETTINGS)):
        line(f"{scenario} S3 - S2 gap", [gap(rows[r], scenario) for r in runs],
             gap(shipped_rows, scenario) if shipped_rows else None)
    for scenario in xvoe.SCENARIOS:
        key = ("holistic", scenario, "")
        line(f"{scenario} holistic AUC (x100)", [rows[r][key] for r in runs],
             shipped_rows[key] if shipped_rows else None)
    if args.hidden_pairs:
        with xvoe.open_dataset(args.data) as file:
            videos = pick(file, "blocking", "S2", 0, args.hidden_pairs)
            ious = {m: hidden_explanations(xvoe.load_model(m), file, videos)["iou"] for m in models}
        line("hidden_iou (x100)", [100 * ious[r] for r in runs], 100 * ious[args.shipped] if args.shipped else None)


if __name__ == "__main__":
    main()
