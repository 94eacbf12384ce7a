"""The MSE score under each explanation, from one pass over a split: the paper's (Transformer 2's
proposal wherever a slot is never seen) against the better of it and no hidden object.

    python benchmarks/explanations.py --model RUN_DIR --data val.h5 --out DIR [--rows FIRST:LAST] [--threads 2]

Prints comparative accuracy per setting and holistic AUC, of the score and of its excess, under
both (95% intervals over pairs), and the share of videos in which "better" leaves the proposed
slot empty, per setting and member. DIR keeps each one's per-video scores (`proposal.csv`,
`better.csv`, as `xvoe score` writes them; `xvoe metrics` reads them). One pass costs about 1.3 times the
paper's score alone: the decodes are shared, the dynamics' prediction is decoded twice.
Choose on a validation split; report on a fresh one (docs/design.md, "Recipes, choosing and shipping").
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

import xvoe
from xvoe.evaluation.metrics import excess
from xvoe.evaluation.scorer import encode_videos
from xvoe.evaluation.surprise import BETTER, EXPLANATIONS, PROPOSED, every_explanation
from xvoe.scenes import store

LABELS = ("scenario", "setting", "pair", "member", "possible")
COLUMNS = ("score", "s_img", "s_dyn", "s_rec", "excess")       # one explanation's, as its own file's score columns
HEADER = ("index", "model", *LABELS, *COLUMNS)


def per_video(scorer, data: str, rows: range, batch: int, progress: bool) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Each explanation's sums over frames (videos, COLUMNS) of the split's `rows`, and which
    videos "better" left empty."""
    sums = {name: [] for name in EXPLANATIONS}
    dropped = []
    with xvoe.open_dataset(data, split="test") as file:
        for start in tqdm(range(rows.start, rows.stop, batch), desc="score", unit="batch", disable=not progress):
            video = encode_videos(scorer, file, start, min(rows.stop, start + batch))
            scored, _ = every_explanation(scorer.vae, scorer.xpl, video["frames"], video["mean"], video["visible"],
                                          video["background"], video["occluder"])
            for name, surprise in scored.items():
                terms = (surprise.s_img + surprise.s_dyn, surprise.s_img, surprise.s_dyn, surprise.s_rec,
                         excess(surprise.s_img, surprise.s_dyn, surprise.s_rec))
                sums[name].append(torch.stack([t.sum(1) for t in terms], 1).double().numpy())
            dropped.append(((scored[PROPOSED].explained_slot >= 0) & (scored[BETTER].explained_slot < 0)).numpy())
    return {name: np.concatenate(parts) for name, parts in sums.items()}, np.concatenate(dropped)


def chosen_rows(data: str, text: str) -> tuple[range, list[np.ndarray]]:
    """The split's rows FIRST:LAST (`row_range`) and their LABELS, read once for every explanation's file."""
    with xvoe.open_dataset(data, split="test") as file:
        rows = row_range(text, file["rgbd"].shape[0])
        return rows, [values[rows.start:rows.stop] for values in store.labels(file, LABELS).values()]


def write(path: Path, labels: list[np.ndarray], rows: range, model: str, values: np.ndarray) -> None:
    """The scores as `xvoe score` writes them (labels, then the sums), for the split's `rows`."""
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(HEADER)
        for i, row in enumerate(values):
            scenario, setting, pair, member, possible = (label[i] for label in labels)
            writer.writerow([rows.start + i, model, scenario, setting, int(pair), int(member), bool(possible),
                             *map(float, row)])


def row_range(text: str, count: int) -> range:
    """FIRST:LAST of the split's rows (either may be left out), checked."""
    first, _, last = text.partition(":")
    rows = range(int(first or 0), int(last or count))
    if not 0 <= rows.start < rows.stop <= count:
        raise SystemExit(f"--rows must lie within 0:{count}, not {text}")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="an XPL run directory or a shipped model's name")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--out", required=True, help="a directory for the per-video scores")
    parser.add_argument("--rows", default=":", help="FIRST:LAST, the split's rows to score (default all; a "
                                                     "1,000-pair split holds each setting in 2,000 rows in a row)")
    parser.add_argument("--batch", type=int, default=16, help="videos per batch")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scorer = xvoe.load_model(args.model)
    if scorer.xpl is None or not scorer.xpl.config.use_reasoning:
        raise SystemExit(f"{args.model} proposes no hidden object: both explanations are the same")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    chosen, labels = chosen_rows(args.data, args.rows)
    sums, dropped = per_video(scorer, args.data, chosen, args.batch, not args.quiet)
    rows = {}
    for name, values in sums.items():
        write(out / f"{name}.csv", labels, chosen, f"{scorer.name}-{name}", values)
        scores = xvoe.read_scores(out / f"{name}.csv")      # the labels as columns; the same for both
        rows[name] = {(r["metric"], r["column"], r["scenario"], r["setting"]): r
                      for r in xvoe.metric_rows(scores, name, ("score", "excess")) if r["metric"] != "relative"}
    print(f"{args.model} on {args.data}: comparative and holistic (x100, 95% interval)")
    print(f"{'metric':<12}{'column':<8}{'scenario':<12}{'setting':<8}" + "".join(f"{n:>22}" for n in EXPLANATIONS))
    for key in rows[PROPOSED]:
        cells = "".join(f"{100 * rows[n][key]['value']:>8.1f} [{100 * rows[n][key]['low']:5.1f}, "
                        f"{100 * rows[n][key]['high']:5.1f}]" for n in EXPLANATIONS)
        print(f"{key[0]:<12}{key[1]:<8}{key[2]:<12}{key[3]:<8}{cells}")
    print("videos in which 'better' leaves the proposed slot empty (%), member 0 / member 1:")
    for scenario, setting in sorted(set(zip(scores["scenario"], scores["setting"]))):
        chosen = (scores["scenario"] == scenario) & (scores["setting"] == setting)
        shares = [100 * dropped[chosen & (scores["member"] == m)].mean() for m in (0, 1)]
        print(f"  {scenario} {setting}: {shares[0]:.0f} / {shares[1]:.0f}")


if __name__ == "__main__":
    main()
