"""Check a CUDA GPU at the paper's preset: every stage trains and scores there, and each step's
time against the device's matrix-product rate. Not yet run on a GPU by the project
(docs/results.md, "On a GPU"): its first user's output is the first measurement.

Two parts, both at `--recipe paper` (128x128, the ViT, the paper's widths):
  stages  a small training split (--videos) and test split (--pairs per setting) are generated;
          every stage of the registry (xvoe.STAGES) and the latent cache between perception and
          the stages on it train --steps steps on the device with the recipe's batch sizes (what
          `xvoe train STAGE --device` does), and every scored model scores the test split (the
          one its registry entry marks with the NLL too, --particles); the wall time of each
  steps   one training step of perception, xpl and phydnet and one MSE and one NLL scoring pass
          on random inputs of the paper's shapes (benchmarks/steps.py's, on the device), timed
          after warm-up; their multiply-accumulates counted (xvoe.evaluation.operations) and
          their rate set against a 4096x4096 matrix product's on the same device, in float32 and
          in bfloat16, the autocast precision of the training and the MSE score there

On a machine without CUDA it says so in one line and exits 0: there is nothing to check.

    python benchmarks/gpu.py
    python benchmarks/gpu.py --device cuda:1 --steps 20 --out gpu-check
"""
from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import steps
import torch

import xvoe
from xvoe import allocator
from xvoe.evaluation.operations import count_operations
from xvoe.models.devices import resolve_device
from xvoe.outputs import claim_directory
from xvoe.training.stages import PERCEPTION, PHYDNET, PROPOSAL, XPL

RECIPE = "paper"


def synchronised(device: torch.device, work: Callable[[], object]) -> float:
    """Seconds of `work` on the device: CUDA runs asynchronously, so the clock waits for it."""
    torch.cuda.synchronize(device)
    start = time.perf_counter()
    work()
    torch.cuda.synchronize(device)
    return time.perf_counter() - start


def matmul_rate(device: torch.device, dtype: torch.dtype, size: int = 4096, repeats: int = 10) -> float:
    """GMAC per second of a size x size matrix product on the device (median of repeats after
    one warm-up), from a CPU generator's draws."""
    generator = torch.Generator().manual_seed(0)
    a, b = (torch.randn(size, size, generator=generator).to(device, dtype) for _ in range(2))
    synchronised(device, lambda: a @ b)
    return size ** 3 / statistics.median(synchronised(device, lambda: a @ b) for _ in range(repeats)) / 1e9


def stages(device: torch.device, out: Path, args: argparse.Namespace) -> None:
    """Every stage trains `args.steps` steps and every scored model scores the test split."""
    size = xvoe.recipe(RECIPE).perception.image_size
    train = xvoe.generate(xvoe.GenerateConfig(split="train", videos=args.videos, size=size, seed=0),
                          out / "train.h5", workers=args.workers, progress=False, overwrite=True)
    test = xvoe.generate(xvoe.GenerateConfig(split="test", pairs=args.pairs, size=size, seed=1),
                         out / "test.h5", workers=args.workers, progress=False, overwrite=True)
    run, cache = out / "run", out / "run" / "latents-train.h5"
    common = dict(steps=args.steps, progress=False, overwrite=True, device=str(device))
    work = {PERCEPTION: lambda: xvoe.train_perception(train, run, recipe_name=RECIPE, **common),
            "encode": lambda: xvoe.encode_split(run, train, cache, overwrite=True, progress=False,
                                                device=device),
            **{stage: (lambda stage=stage: xvoe.train_xpl(cache, run, stage=stage, recipe_name=RECIPE, **common))
               for stage, entry in xvoe.STAGES.items() if entry.reads == "latents"},
            PROPOSAL: lambda: xvoe.train_proposal(run, **common),
            PHYDNET: lambda: xvoe.train_phydnet(train, run, recipe_name=RECIPE, **common)}
    for model in (name for name, entry in xvoe.STAGES.items() if entry.scored):
        surprise = "both" if xvoe.STAGES[model].nll else "mse"
        work[f"score {model} ({surprise})"] = lambda model=model, surprise=surprise: xvoe.score(
            str(run / f"{model}.pt"), test, out / f"{model}.csv", surprise=surprise, particles=args.particles,
            overwrite=True, progress=False, device=str(device))
    videos = 22 * args.pairs      # 11 test settings, a pair of videos each
    print(f"stages: {args.steps} training steps each at the recipe's batch sizes; {videos} test videos scored")
    for name, job in work.items():
        print(f"  {name:<28} {synchronised(device, job):8.1f} s", flush=True)


def step_rates(device: torch.device, args: argparse.Namespace) -> None:
    """Each step's time and its rate as a fraction of the matrix product's, in float32 and bfloat16."""
    chosen = xvoe.recipe(RECIPE)
    where = str(device)
    builders = {
        PERCEPTION: lambda rng: (steps.perception_step(chosen.perception, args.frames, rng, where), args.frames),
        XPL: lambda rng: (steps.xpl_step(chosen.xpl, args.step_videos, rng, where), args.step_videos),
        PHYDNET: lambda rng: (steps.phydnet_step(chosen.phydnet, args.phydnet_videos, rng, where),
                              args.phydnet_videos),
        "score": lambda rng: (steps.score_step(chosen.perception, chosen.xpl, args.score_videos, rng, where),
                              args.score_videos),
        "nll": lambda rng: (steps.nll_step(chosen.perception, chosen.xpl, chosen.nll, rng, where), 1)}
    peaks = {"float32": matmul_rate(device, torch.float32), "bfloat16": matmul_rate(device, torch.bfloat16)}
    print(f"steps: a 4096x4096 matrix product runs at {peaks['float32']:.0f} GMAC/s in float32, "
          f"{peaks['bfloat16']:.0f} in bfloat16")
    print(f"  {'step':<12} {'ms/item':>9} {'GMAC/item':>10} {'GMAC/s':>9} {'of fp32':>8} {'of bf16':>8}  items/step")
    for name, build in builders.items():
        torch.manual_seed(args.seed)
        step, items = build(np.random.default_rng(args.seed))
        for _ in range(args.warmup):
            step()
        seconds = statistics.median(synchronised(device, step) for _ in range(args.repeats))
        gmacs = count_operations(step).gmacs
        rate = gmacs / seconds
        print(f"  {name:<12} {1000 * seconds / items:9.2f} {gmacs / items:10.2f} {rate:9.0f} "
              f"{rate / peaks['float32']:8.1%} {rate / peaks['bfloat16']:8.1%}  {items} {steps.UNIT[name]}s",
              flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda", help="the CUDA device to check (default cuda)")
    parser.add_argument("--parts", default="stages,steps", help="stages, steps or both (default)")
    parser.add_argument("--out", help="where the stages write (default: a temporary directory, removed)")
    parser.add_argument("--steps", type=int, default=10, help="training steps of each stage")
    parser.add_argument("--videos", type=int, default=200, help="training videos generated")
    parser.add_argument("--pairs", type=int, default=2, help="test pairs per setting generated and scored")
    parser.add_argument("--particles", type=int, default=64, help="the NLL's particles")
    parser.add_argument("--workers", type=int, default=2, help="generation workers")
    parser.add_argument("--frames", type=int, default=36, help="frames per perception step (the recipe's 36)")
    parser.add_argument("--step-videos", type=int, default=64, help="videos per XPL step")
    parser.add_argument("--phydnet-videos", type=int, default=16, help="videos per PhyDNet step")
    parser.add_argument("--score-videos", type=int, default=16, help="videos per MSE scoring pass")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    if not torch.cuda.is_available():
        print(f"benchmarks/gpu.py: no CUDA device on this machine (torch {torch.__version__}); nothing to check")
        return 0
    try:
        device = resolve_device(args.device)
    except xvoe.XvoeError as error:
        print(f"benchmarks/gpu.py: {error}", file=sys.stderr)
        return 2
    print(f"{torch.cuda.get_device_name(device)}, torch {torch.__version__}, CUDA {torch.version.cuda}, "
          f"recipe {RECIPE}")
    parts = args.parts.split(",")
    if "stages" in parts:
        if args.out:
            stages(device, claim_directory(args.out), args)
        else:
            with tempfile.TemporaryDirectory(prefix="xvoe-gpu-") as out:
                stages(device, Path(out), args)
    if "steps" in parts:
        step_rates(device, args)
    return 0


if __name__ == "__main__":
    allocator.tune()        # timed as the command line runs: with its malloc settings
    sys.exit(main())
