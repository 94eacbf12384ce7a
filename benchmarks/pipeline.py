"""The default pipeline, measured: wall time per stage, peak memory, and the goals
(docs/design.md, "Goals") that the pipeline's own models show on a fresh test set.

    python benchmarks/pipeline.py --out runs/bench [--recipe cpu-short] [--seed 0] [--models xpl,random]
                                  [--fresh-pairs 1000 | --fresh split.h5] [--budget 0.4]

Runs `xvoe pipeline` (skipping stages a previous run finished) and prints each stage's time
from the run's own records, so that a resumed run still reports its whole time. Then scores a
fresh test set (a seed neither training nor the pipeline's test split used, nor any choice;
or an existing split with --fresh) with every model and checks the goals: the time
(20 minutes for the default models, 90 for all five, on 2 cores without AVX-512) and memory (4 GiB); XPL's S1 and S3 >=
97% in every scenario; PLATO's and PhyDNet's S1 >= 90%; XPL's S3 above theirs by >= 20 points
in collision and blocking; random at 50% within its interval (xvoe.evaluation.scorecard's
lines). The goals that need the NLL or the model itself (hidden_iou, NLL-excess AUC, the
perception's) are benchmarks/scorecard.py's.
"""
from __future__ import annotations

import argparse
import resource
import time
from dataclasses import replace
from pathlib import Path

import xvoe
from xvoe.apps.pipeline import scored_reference, stage_times
from xvoe.evaluation import scorecard
from xvoe.training.config import TrainConfig
from xvoe.training.stages import BASELINE, DEFAULT_MODELS, MODELS, XPL

FRESH_SEED = 12345


def peak_memory_gib() -> float:
    """Largest resident set of this process or any finished child, GiB (Linux: KiB units)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(own, children) / 2**20


def time_goal(models: tuple[str, ...]) -> float | None:
    """The budget in minutes for these models (docs/design.md, "Goals"): the default models or all five."""
    if set(models) >= set(MODELS):
        return 90.0
    return 20.0 if set(models) <= set(DEFAULT_MODELS) else None


def within_budget(name: str, fraction: float) -> str:
    """A recipe like `name` with every stage's steps and decay steps times `fraction`, registered
    in this process (its stages' processes get it from `on_cores`); its name."""
    if fraction == 1.0:
        return name
    if not 0.0 < fraction < 1.0:
        raise SystemExit(f"--budget must be above 0 and at most 1, not {fraction}")
    chosen = xvoe.recipe(name)

    def scaled(train: TrainConfig | None) -> TrainConfig | None:     # None: the stage trains as xpl_train says
        if train is None:
            return None
        return replace(train, steps=max(1, round(train.steps * fraction)),
                       decay_steps=max(1, round(train.decay_steps * fraction)))

    fields = {entry.train_field for entry in xvoe.STAGES.values()}
    trainings = {field: scaled(getattr(chosen, field)) for field in fields}
    budget = f"{name}-x{fraction:g}"
    phases = tuple((stage, scaled(train)) for stage, train in chosen.phases)
    xvoe.RECIPES[budget] = replace(chosen, name=budget, phases=phases, **trainings)
    return budget


def accuracy_lines(found: dict[str, dict]) -> list[scorecard.Line]:
    """Section 7's comparative goals from each model's scores, one line each, named by model,
    and XPL's S3 lead over the baselines."""
    lines = [replace(line, name=f"{model} {line.name}") for model, scores in found.items()
             for line in scorecard.score_lines(scores, scorecard.role_of(model))]
    if XPL in found:
        baselines = {m: scores for m, scores in found.items() if scorecard.role_of(m) == BASELINE}
        lines += scorecard.lead_lines(found[XPL], baselines)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--recipe", default=xvoe.DEFAULT_RECIPE)
    parser.add_argument("--seed", type=int, default=0, help="the training seed (xvoe pipeline --seed)")
    parser.add_argument("--train-videos", type=int, help="default: the recipe's")
    parser.add_argument("--pairs", type=int, default=200)
    parser.add_argument("--models", default=",".join(DEFAULT_MODELS))
    parser.add_argument("--fresh", help="an existing fresh test split (a seed nothing was chosen on) to score")
    parser.add_argument("--fresh-pairs", type=int, default=1000, help="pairs per setting of the fresh split made")
    parser.add_argument("--fresh-seed", type=int, default=FRESH_SEED)
    parser.add_argument("--budget", type=float, default=1.0, help="the share of the recipe's training steps")
    args = parser.parse_args()
    args.recipe = within_budget(args.recipe, args.budget)
    models = tuple(args.models.split(","))
    run_dir = Path(args.out)
    finished_before = set(stage_times(run_dir))
    start = time.monotonic()
    report = xvoe.run_pipeline(xvoe.PipelineConfig(args.out, args.recipe, args.train_videos, args.pairs, models,
                                         seed=args.seed, progress=False))
    wall = time.monotonic() - start
    stages = stage_times(run_dir)
    minutes = sum(stages.values()) / 60
    print(f"pipeline: {wall / 60:.1f} min wall this run, report {report}")
    for name, seconds in stages.items():
        print(f"  {name}: {seconds:.1f} s")
    budget = time_goal(models)
    print(scorecard.format_line(scorecard.Line("pipeline minutes, every stage", minutes, target=budget,
                                               direction="<=")))
    # stages finished by an earlier run ran in other processes: their memory is not measured here
    ran = [name for name in stages if name not in finished_before]
    if ran:
        memory = peak_memory_gib()
        print(scorecard.format_line(scorecard.Line(f"peak memory of this run's {len(ran)} stage(s) (GiB)", memory,
                                                   target=4.0, direction="<=")))
    else:
        print("peak memory: not measured (every stage finished in an earlier run)")

    fresh = Path(args.fresh) if args.fresh else run_dir / "data" / f"fresh-{args.fresh_seed}.h5"
    if not fresh.exists():
        size = xvoe.recipe(args.recipe).perception.image_size
        fresh_split = xvoe.GenerateConfig("test", pairs=args.fresh_pairs, size=size, seed=args.fresh_seed)
        xvoe.generate(fresh_split, fresh, workers=2, progress=False)
    found = {}
    for model in models:
        out = run_dir / "scores" / f"fresh-{fresh.stem}-{model}.csv"
        start = time.monotonic()
        scores = xvoe.read_scores(xvoe.score(scored_reference(run_dir, model), fresh, out, overwrite=True,
                                             progress=False))
        print(f"{model}: scored {len(scores['index'])} videos of {fresh} in {time.monotonic() - start:.0f} s")
        found[model] = scores
    for line in accuracy_lines(found):
        print(scorecard.format_line(line))


if __name__ == "__main__":
    main()
