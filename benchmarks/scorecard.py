"""Every goal of DESIGN section 7 that one model's run can measure, one line each, met or not.

    python benchmarks/scorecard.py --model xpl --data val.h5 [--particles 64] [--seeds 0,1]
                                   [--pairs 100] [--json card.json]

Scores the split with both surprise definitions (`xvoe score --surprise both`), then reads:
comparative accuracy per setting under the MSE score, its excess, the NLL and the NLL excess;
the S3 - S2 gap per scenario; holistic AUC per definition and scenario; hidden_iou and mae_iou
(benchmarks/explanation.py, on --pairs videos); p_hidden on videos with a never-seen object and
on all-seen ones; the ESS among object-holding particles; the NLL's repeatability between
--seeds; videos per second of each definition. Goals across models (XPL's S3 lead over PLATO
and PhyDNet, random at chance) need each model's card. Choose on validation seeds, report on
fresh ones (DESIGN section 8).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from explanation import hidden_iou, mae_iou, pick
from nll import ground_truth

import xvoe
from xvoe.benchmark import store

SCENARIOS = ("collision", "blocking", "permanence", "continuity")


def goal(name: str, value: float, target: float, above: bool = True) -> dict:
    met = bool(value >= target) if above else bool(value <= target)
    return {"goal": name, "value": float(value), "target": target, "direction": ">=" if above else "<=", "met": met}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a shipped model's name or a run directory")
    parser.add_argument("--data", required=True, help="a validation or report split at the model's resolution")
    parser.add_argument("--particles", type=int, default=64)
    parser.add_argument("--seeds", default="0,1",
                        help="the NLL's seeds; the first scores, the second measures repeatability")
    parser.add_argument("--pairs", type=int, default=100, help="videos for hidden_iou and mae_iou")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", help="write the card here too")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds = [int(s) for s in args.seeds.split(",")]
    model = xvoe.load_model(args.model)
    work = Path(tempfile.mkdtemp(prefix="scorecard-"))

    start = time.perf_counter()
    mse_csv = xvoe.score(model, args.data, work / "mse.csv", progress=False)
    mse_seconds = time.perf_counter() - start
    start = time.perf_counter()
    runs = [xvoe.score(model, args.data, work / f"nll-{seed}.csv", surprise="both", particles=args.particles,
                       seed=seed, progress=False) for seed in seeds]
    nll_seconds = (time.perf_counter() - start) / len(seeds)
    scores = xvoe.read_scores(runs[0])
    count = len(scores["index"])
    card = []
    # the comparative goals: the MSE score's (DESIGN section 7) and the NLL's (issue on SMC); the
    # excess columns are measured, with no goal of their own
    targets = {"score": 97.0, "excess": None, "nll": 99.0, "nll_excess": None}
    for column, label in (("score", "MSE"), ("excess", "MSE excess"), ("nll", "NLL"), ("nll_excess", "NLL excess")):
        accuracy = {(r["scenario"], r["setting"]): r["value"] for r in xvoe.metric_rows(scores, "m", (column,))
                    if r["metric"] == "comparative"}
        for (scenario, setting), value in accuracy.items():
            if setting in ("S1", "S3"):
                name = f"{label} {scenario} {setting} comparative"
                card.append(goal(name, 100 * value, targets[column]) if targets[column]
                            else {"goal": name, "value": 100 * value})
        if column == "score":
            for scenario in SCENARIOS:
                if (scenario, "S3") in accuracy and (scenario, "S2") in accuracy:
                    gap = 100 * (accuracy[scenario, "S3"] - accuracy[scenario, "S2"])
                    card.append({"goal": f"S3 - S2 gap {scenario} (reported, no goal)", "value": gap})
        for row in xvoe.metric_rows(scores, "m", (column,)):
            if row["metric"] == "holistic":
                target = 0.9 if column == "nll_excess" else None
                line = {"goal": f"{label} {row['scenario']} holistic AUC", "value": row["value"]}
                card.append(goal(line["goal"], row["value"], target) if target else line)

    with store.open_dataset(args.data) as file:
        names, columns = list(file.attrs["kind_names"]), list(file["states"].attrs["state_columns"])
        kinds = np.array([ground_truth(file, int(i), names, columns) for i in scores["index"]])
        card.append(goal("hidden_iou", hidden_iou(model, file, pick(file, "blocking", "S2", 0, args.pairs), names,
                                                  columns), 0.6))
        expected = [i for s in SCENARIOS for i in pick(file, s, "S1", 0, max(1, args.pairs // 4))]
        card.append({"goal": "mae_iou (reported, no goal)", "value": mae_iou(model, file, expected, names, columns)})
    hidden, seen = kinds == "hidden", kinds == "seen"
    if hidden.any():
        card.append(goal("p_hidden > 0.5 on never-seen-object videos (%)",
                         100 * np.mean(scores["p_hidden"][hidden] > 0.5), 95.0))
        card.append(goal(f"ESS among object-holding particles of {args.particles}, never-seen videos (median)",
                         np.median(scores["ess"][hidden]), args.particles / 4))
    card.append(goal("p_hidden < 0.5 on all-seen videos (%)", 100 * np.mean(scores["p_hidden"][seen] < 0.5), 95.0))
    card.append({"goal": "ESS among object-holding particles, all videos (median, reported)",
                 "value": float(np.median(scores["ess"]))})
    if len(runs) > 1:
        other = xvoe.read_scores(runs[1])
        differences = np.abs(scores["nll"] - other["nll"])
        card.append(goal("NLL repeatability, two seeds, median (nats)", np.median(differences), 0.5, above=False))
        card.append(goal("NLL repeatability, two seeds, 99th percentile (nats)", np.percentile(differences, 99), 5.0,
                         above=False))
    card.append(goal("MSE scoring, videos per second", count / mse_seconds, 10.0))
    card.append(goal("NLL scoring (with MSE), videos per second", count / nll_seconds, 5.0))

    for line in card:
        status = "" if "met" not in line else ("  met" if line["met"] else "  NOT MET")
        target = f" (goal {line['direction']} {line['target']:g})" if "target" in line else ""
        print(f"{line['goal']}: {line['value']:.3f}{target}{status}")
    print(f"{sum(1 for line in card if line.get('met'))} of {sum(1 for line in card if 'met' in line)} goals met; "
          f"{count} videos of {args.data}, model {args.model}; MSE scores in {mse_csv}")
    if args.json:
        Path(args.json).write_text(json.dumps({"model": args.model, "data": str(args.data), "card": card}, indent=1))


if __name__ == "__main__":
    main()
