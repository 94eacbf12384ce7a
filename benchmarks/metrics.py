"""Time of `xvoe metrics` on scores files: the bootstrap of every metric, and the whole report.

    python benchmarks/metrics.py runs/default/scores/xpl.csv runs/default/scores/random.csv [--rounds 1000]

Last line: metric_rows_s=N.N report_s=N.N (metric_rows: every metric and component of every
file with its bootstrap interval; report: that plus the tables and figures).
"""
from __future__ import annotations

import argparse
import tempfile
import time

import xvoe
from xvoe.evaluation import score_tables


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scores", nargs="+")
    parser.add_argument("--rounds", type=int, default=1000)
    args = parser.parse_args()
    start = time.perf_counter()
    rows = 0
    for path in args.scores:
        scores = xvoe.read_scores(path)
        rows += len(xvoe.metric_rows(scores, score_tables.model_name(path, scores), rounds=args.rounds))
    rows_s = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        xvoe.report(args.scores, out, rounds=args.rounds, overwrite=True)
        report_s = time.perf_counter() - start
    print(f"{len(args.scores)} files, {rows} metric rows, {args.rounds} bootstrap rounds")
    print(f"metric_rows_s={rows_s:.1f} report_s={report_s:.1f}")


if __name__ == "__main__":
    main()
