"""What pinning the kernels costs: a recipe's training and scoring steps (benchmarks/steps.py)
timed under the kernels every training process pins (`xvoe.training.distributed.KERNELS`: AVX2 for
torch's own kernels and oneDNN's, MKL's maker-independent path) against this machine's own
choice, each in a fresh process (a process's kernels are fixed at its first), alternated
`--rounds` times. It prints each stage's median ms per item under both and their ratio.

    python benchmarks/kernels.py --stages perception,xpl,phydnet,score --threads 1,2

On a host without AVX-512 torch's and oneDNN's choices are AVX2 already: the ratio there is
MKL's alone, which `--baseline avx2` estimates on a host with AVX-512 (torch's and oneDNN's
kernels at AVX2 in both runs, MKL's own choice against its pinned path). Time it on an idle machine.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

from xvoe import allocator
from xvoe.training.distributed import KERNELS

STEPS = Path(__file__).with_name("steps.py")


def timed(pinned: bool, args: argparse.Namespace) -> dict[tuple[str, str], float]:
    """(stage, threads) -> ms per item, from one run of steps.py in a fresh process."""
    env = {name: value for name, value in os.environ.items() if name not in KERNELS}
    if pinned:
        env |= KERNELS
    elif args.baseline == "avx2":
        env |= {name: value for name, value in KERNELS.items() if name != "MKL_CBWR"}
    command = [sys.executable, str(STEPS), "--recipe", args.recipe, "--stages", args.stages, "--threads",
               args.threads, "--repeats", str(args.repeats)]
    lines = subprocess.run(command, env=env, capture_output=True, text=True, check=True).stdout.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("stage "))
    found = {}
    for line in lines[header + 1:]:
        fields = line.split()
        if len(fields) > 3 and fields[1].isdigit():
            found[(fields[0], fields[1])] = float(fields[2])
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recipe", default="cpu-short")
    parser.add_argument("--stages", default="perception,xpl,phydnet,score")
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--repeats", type=int, default=5, help="timed steps per run of steps.py")
    parser.add_argument("--rounds", type=int, default=3, help="runs of each, alternated")
    parser.add_argument("--baseline", choices=("own", "avx2"), default="own",
                        help="against this machine's own kernels, or torch's and oneDNN's at AVX2 with MKL's own")
    args = parser.parse_args()
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    print(f"host: {'with' if 'avx512f' in flags else 'without'} AVX-512; baseline: {args.baseline}; pinned: "
          + " ".join(f"{name}={value}" for name, value in KERNELS.items()))
    runs: dict[bool, list[dict]] = {True: [], False: []}
    for _ in range(args.rounds):
        for pinned in (False, True):
            runs[pinned].append(timed(pinned, args))
    print(f"{'stage':<12} {'threads':>7} {'own ms/item':>12} {'pinned ms/item':>15} {'pinned / own':>13}")
    for key in runs[False][0]:
        own = statistics.median(run[key] for run in runs[False])
        pinned = statistics.median(run[key] for run in runs[True])
        print(f"{key[0]:<12} {key[1]:>7} {own:>12.2f} {pinned:>15.2f} {pinned / own:>13.2f}")


if __name__ == "__main__":
    allocator.tune()        # timed as the command line runs: with its malloc settings
    main()
