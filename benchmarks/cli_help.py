"""How long `xvoe --help` and `xvoe VERB --help` take, against `python -c pass`: the command
line's parser imports nothing of torch, so its help answers at about interpreter speed (goal:
<= 0.5 s on an idle core, docs/design.md "Goals"; figures in docs/results.md, "Speed").

Each command runs in a fresh interpreter (this one's), `--repeats` times; the median is printed.

    python benchmarks/cli_help.py
    python benchmarks/cli_help.py --repeats 9 --verbs score,train
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time

from xvoe.cli import build_parser

BASELINE = ["-c", "pass"]


def verbs() -> list[str]:
    """Every verb of the command line, from its parser."""
    return list(build_parser()._subparsers._group_actions[0].choices)


def seconds(args: list[str], repeats: int) -> float:
    """Median wall time of `python ARGS` over `repeats` runs, one thread."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, *args], env=env, check=True, stdout=subprocess.DEVNULL)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs per command (default 5)")
    parser.add_argument("--verbs", help="comma-separated verbs (default: every one)")
    args = parser.parse_args()
    chosen = args.verbs.split(",") if args.verbs else verbs()
    base = seconds(BASELINE, args.repeats)
    print(f"{'command':<28} {'seconds':>8} {'over pass':>10}")
    print(f"{'python -c pass':<28} {base:8.3f} {0:10.3f}")
    for argv in [["--help"], *([verb, "--help"] for verb in chosen)]:
        took = seconds(["-m", "xvoe", *argv], args.repeats)
        print(f"{'xvoe ' + ' '.join(argv):<28} {took:8.3f} {took - base:10.3f}")


if __name__ == "__main__":
    main()
