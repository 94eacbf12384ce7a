"""The verbs of a whole run: `pipeline` makes one end to end, `ship` makes its models the shipped ones.

Each verb's parser sits beside what it runs; both call the public API, as a notebook does."""
from __future__ import annotations

import argparse

import xvoe

from ..domains import NON_NEGATIVE, SEED, Domain
from ..training.config import DEFAULT_RECIPE
from ..training.stages import DEFAULT_MODELS, MODELS, SCORED
from .arguments import add_device, default_workers, flag, latent_stages, positive, recipe_names

__all__ = ["add_pipeline", "add_ship"]


def add_pipeline(verbs) -> None:
    pipeline = verbs.add_parser("pipeline", help="generate, train, score and report, end to end",
                                description="Generate the benchmark, train every stage, score the test split, "
                                            "compute the metrics and write RUN_DIR/report.md. A rerun skips "
                                            "the stages already done and resumes an interrupted one.")
    pipeline.add_argument("--out", required=True, help="the run directory")
    pipeline.add_argument("--recipe", default=DEFAULT_RECIPE,
                          help=f"every stage and setting of the models: {recipe_names()}")
    pipeline.add_argument("--train-videos", type=positive, help="training videos (default: the recipe's, 10000)")
    pipeline.add_argument("--pairs", type=positive, default=200, help="test pairs per setting (default 200)")
    pipeline.add_argument("--models", default=",".join(DEFAULT_MODELS),
                          help=f"comma-separated: {', '.join(MODELS)} (default {','.join(DEFAULT_MODELS)})")
    pipeline.add_argument("--seed", type=flag(int, Domain(0, SEED.high - 1), "seed"), default=0,
                          help="training seed; the test split uses seed + 1")
    pipeline.add_argument("--workers", type=positive, default=default_workers(), help="generation workers")
    pipeline.add_argument("--jobs", type=flag(int, NON_NEGATIVE, "jobs"), default=1,
                          help="models trained side by side, the cores shared out (0: one per core; default 1: "
                               "one at a time); more lanes hold more memory")
    pipeline.add_argument("--train-processes", type=int, default=0,
                          help=f"one-thread processes that train the {latent_stages()} stages together "
                               "(default 0: one per core), at most as many as a stage has data shards and a "
                               "divisor of them, so that the batches are the same on any machine")
    pipeline.add_argument("--quiet", action="store_true", help="no progress bars")
    add_device(pipeline, "every stage (training, encoding, scoring)")
    # a seed trains the same bytes anywhere: `main` pins the kernels before any runs
    pipeline.set_defaults(run=_run_pipeline, pins_kernels=True)


def _run_pipeline(args: argparse.Namespace) -> None:
    models = tuple(m.strip() for m in args.models.split(",") if m.strip())
    print(xvoe.run_pipeline(xvoe.PipelineConfig(args.out, args.recipe, args.train_videos, args.pairs, models,
                                                args.seed, args.workers, not args.quiet, args.jobs,
                                                args.train_processes, args.device)))


def add_ship(verbs) -> None:
    ship = verbs.add_parser("ship", help=f"make a run's models the shipped ones ({', '.join(SCORED[:2])}, ...)",
                            description="Copy RUN_DIR's checkpoints, stripped to weights and configs, into "
                                        f"the package's weights directory, where --model {SCORED[0]} finds them.")
    ship.add_argument("run_dir", help="the run directory (of xvoe pipeline)")
    ship.add_argument("--out", help="another directory to write to (default: the package's)")
    ship.add_argument("--quiet", action="store_true", help="the paths written, without their sizes")
    ship.set_defaults(run=_run_ship)


def _run_ship(args: argparse.Namespace) -> None:
    for path in xvoe.ship(args.run_dir, args.out):
        print(path if args.quiet else f"{path}  {path.stat().st_size / 2**20:.1f} MB")
