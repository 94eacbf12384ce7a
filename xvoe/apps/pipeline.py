"""`xvoe pipeline`: generate, train every stage, score, measure and report, in one directory.

Each stage writes its output into RUN_DIR and then a marker under RUN_DIR/.done; a rerun
skips the stages already done and resumes an interrupted training stage from its
checkpoint, so an interrupted pipeline loses at most a few minutes of work.

    RUN_DIR/data/train.h5, data/test.h5    the benchmark (test seed never used for training)
    RUN_DIR/perception.pt, latents-train.h5
    RUN_DIR/xpl.pt (plato.pt, xpl-noresidual.pt, phydnet.pt)
    RUN_DIR/scores/MODEL.csv               one row per test video, and MODEL.curves.npz
    RUN_DIR/report/                        metrics.csv, metrics.json, figures
    RUN_DIR/report.md                      one page with the numbers and the figures
"""
from __future__ import annotations

import csv
import json
import multiprocessing
import os
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from ..errors import XvoeError
from ..evaluation.explain import explain
from ..evaluation.scorecard import role_of
from ..evaluation.scorer import load_model
from ..models.config import to_dict
from ..models.devices import resolve_device
from ..outputs import claim_directory, claim_scope
from ..processes import end_with_parent
from ..resources import check_workers, cores
from ..scenes import store
from ..scenes.generate import GenerateConfig, generate
from ..training.config import TrainConfig
from ..training.data import process_counts
from ..training.latents import encode_split
from ..training.launch import on_cores
from ..training.loop import checkpoint_path
from ..training.perception import train_perception
from ..training.phydnet import train_phydnet
from ..training.proposal import train_proposal
from ..training.recipes import DEFAULT_RECIPE, RECIPES, Recipe, recipe
from ..training.stages import CHANCE, DEFAULT_MODELS, MODELS, PERCEPTION, STAGES, XPL, continued_by, resting_on
from ..training.xpl import TRAINED_ON_LATENTS, train_xpl
from .explanation_figure import plot_explanation
from .report import header_lines, report
from .verbs import score, with_display

__all__ = ["PipelineConfig", "Stages", "run_pipeline", "stage_times", "run_files", "scored_reference",
           "scored_steps", "stage_processes", "compare_models", "write_report"]


@dataclass(frozen=True)
class PipelineConfig:
    out: str
    recipe: str = DEFAULT_RECIPE
    train_videos: int | None = None     # None: the recipe's
    pairs: int = 200
    models: tuple[str, ...] = DEFAULT_MODELS
    seed: int = 0
    workers: int = 2
    progress: bool = True
    jobs: int = 1       # models trained side by side, each with cores/jobs threads (0: one per core); they hold
                        # more memory together (docs/decisions.md, "Processes and threads")
    train_processes: int = 0    # one-thread processes that train the XPL, proposal and PLATO stages together (0:
                                # one per core; with --jobs above 1, each lane trains in one process); fewer
                                # where a stage's data shards do not split among them (`stage_processes`)
    device: str = "cpu"         # where every stage trains, encodes and scores (cpu, cuda, cuda:N, mps)

    def __post_init__(self) -> None:
        resolve_device(self.device)
        if not self.models:
            raise XvoeError(f"--models names no model; choose from {', '.join(MODELS)}")
        unknown = [m for m in self.models if m not in MODELS]
        if unknown:
            raise XvoeError(f"unknown model(s) {', '.join(unknown)}; choose from {', '.join(MODELS)}")
        if (self.train_videos is not None and self.train_videos < 1) or self.pairs < 1:
            raise XvoeError("--train-videos and --pairs must be at least 1")
        if self.jobs < 0:
            raise XvoeError("--jobs must be 0 (one per core) or more")
        if self.train_processes < 0:
            raise XvoeError("--train-processes must be 0 (one per core) or more")


class Stages:
    """Runs named stages once; a stage is done when its marker exists (and, for a stage given
    a key, such as the models a report covers, when the marker holds the same key)."""

    def __init__(self, run_dir: Path, progress: bool):
        self.run_dir, self.progress = run_dir, progress
        self.marks = run_dir / ".done"
        self.marks.mkdir(parents=True, exist_ok=True)
        self.timings: dict[str, float] = {}

    def done(self, name: str, key: str = "") -> bool:
        mark = self.marks / name
        return mark.exists() and (not key or mark.read_text().splitlines()[1:] == [key])

    def run(self, name: str, work: Callable[[], object], key: str = "") -> None:
        if self.done(name, key):
            return
        if self.progress:
            print(f"[pipeline] {name}", flush=True)
        # an interrupted stage's time so far, so that the resumed one reports its whole time
        partial = self.run_dir / ".partial" / name
        before = float(partial.read_text()) if partial.exists() else 0.0
        start = time.monotonic()
        try:
            work()
        except BaseException:
            partial.parent.mkdir(exist_ok=True)
            partial.write_text(f"{before + time.monotonic() - start:.1f}")
            raise
        self.timings[name] = before + time.monotonic() - start
        partial.unlink(missing_ok=True)
        (self.marks / name).write_text(f"{self.timings[name]:.1f} s\n" + (f"{key}\n" if key else ""))


@claim_scope()
def run_pipeline(config: PipelineConfig) -> Path:
    """Everything, end to end; returns the path of report.md."""
    chosen = recipe(config.recipe)
    check_workers(config.workers)
    size, train_videos = chosen.perception.image_size, config.train_videos or chosen.train_videos
    run_dir = claim_directory(config.out, whole=True)     # one pipeline in a run directory at a time
    (run_dir / "data").mkdir(exist_ok=True)
    stages = Stages(run_dir, config.progress)
    train_data, test_data, latents = run_files(run_dir)

    stages.run("generate-train", lambda: generate(
        GenerateConfig("train", videos=train_videos, size=size, seed=config.seed), train_data,
        workers=config.workers, overwrite=True, progress=config.progress))
    stages.run("generate-test", lambda: generate(
        GenerateConfig("test", pairs=config.pairs, size=size, seed=config.seed + 1), test_data,
        workers=config.workers, overwrite=True, progress=config.progress))
    processes = config.train_processes or cores()
    on_device = resolve_device(config.device).type != "cpu"
    if on_device:       # lanes and one-thread processes share out CPU cores; one process drives a device
        processes = 1
    if any(model in TRAINED_ON_LATENTS for model in config.models):     # PhyDNet and the random agent need none
        # one process with every core's thread: its convolutions use them (docs/decisions.md, "Processes
        # and threads")
        stages.run(PERCEPTION, lambda: train_perception(
            train_data, run_dir, recipe_name=config.recipe, progress=config.progress,
            resume=checkpoint_path(run_dir, PERCEPTION).exists(), seed=config.seed, device=config.device))
        stages.run("encode-train", lambda: encode_split(run_dir, train_data, latents, overwrite=True,
                                                        progress=config.progress, device=config.device))
    (run_dir / "scores").mkdir(exist_ok=True)
    heavy = sorted((m for m in config.models if m in STAGES), key=lambda m: STAGES[m].lane)
    lanes = 1 if on_device else min(config.jobs or cores(), len(heavy))
    if lanes > 1:       # one model's training per lane, the cores shared out: two 1-thread runs beat one 2-thread run
        threads = max(1, cores() // lanes)
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(lanes, mp_context=context, initializer=end_with_parent,
                                 initargs=(os.getpid(),)) as pool:
            for done in [pool.submit(_lane, config, recipe(config.recipe), model, threads) for model in heavy]:
                done.result()
    for model in config.models:
        _model_stages(config, model, stages, config.progress, processes=processes)
    scores = [run_dir / "scores" / f"{model}.csv" for model in config.models]
    # a rerun with more models, or with a model trained further, redoes what covers them all
    steps = (scored_steps(chosen, model) for model in config.models)
    models = ",".join(config.models) + "; " + "; ".join(filter(None, steps))

    def metrics() -> None:
        report(scores, run_dir / "report", seed=config.seed, overwrite=True)

    stages.run("metrics", metrics, key=models)
    stages.run("explanations", lambda: _explanations(run_dir, test_data, config.models, config.device), key=models)
    return write_report(run_dir, config)


def stage_times(run_dir: Path) -> dict[str, float]:
    """Each finished stage's seconds, as its marker holds them (a resumed stage's whole time)."""
    marks = run_dir / ".done"
    return {mark.name: float(mark.read_text().split()[0]) for mark in sorted(marks.iterdir())} if marks.exists() else {}


def run_files(run_dir: Path) -> tuple[Path, Path, Path]:
    """Where a run keeps its training split, its test split and the training split's latent cache."""
    return run_dir / "data" / "train.h5", run_dir / "data" / "test.h5", run_dir / "latents-train.h5"


def _model_stages(config: PipelineConfig, model: str, stages: Stages, bars: bool, scoring: bool = True,
                  processes: int = 1) -> None:
    """Train (with the proposal stage for xpl) and score one model, skipping what is done; the
    XPL, proposal and PLATO stages in up to `processes` one-thread processes (`stage_processes`)."""
    run_dir = Path(config.out)
    train_data, test_data, latents = run_files(run_dir)
    chosen = recipe(config.recipe)
    phases = chosen.phases_of(model)
    if model in TRAINED_ON_LATENTS:
        def train(phase: dict) -> object:
            return on_cores(train_xpl, stage_processes(processes, chosen.training(model)), chosen, latents=latents,
                            run_dir=run_dir, stage=model, recipe_name=config.recipe, progress=bars,
                            resume=checkpoint_path(run_dir, model).exists(), device=config.device, **phase)
        _train_phases(stages, model, train, phases, config.seed)
        for then in continued_by(model):       # the proposal stage, after xpl
            stages.run(f"train-{then}", lambda then=then: on_cores(
                train_proposal, stage_processes(processes, chosen.training(then)), chosen, run_dir=run_dir,
                latents=latents, progress=bars, device=config.device,
                resume=checkpoint_path(run_dir, then).exists(), seed=config.seed))
    elif model in STAGES and STAGES[model].reads == "pixels":     # PhyDNet
        def train(phase: dict) -> object:
            return train_phydnet(train_data, run_dir, recipe_name=config.recipe, progress=bars,
                                 resume=checkpoint_path(run_dir, model).exists(), device=config.device,
                                 **phase)
        _train_phases(stages, model, train, phases, config.seed)
    if not scoring:
        return
    stages.run(f"score-{model}", lambda: score(
        scored_reference(run_dir, model), str(test_data), str(run_dir / "scores" / f"{model}.csv"), overwrite=True,
        progress=bars, device=config.device),
        key=scored_steps(chosen, model))


def scored_reference(run_dir: Path, model: str) -> str:
    """What `load_model` takes for a model of the run: its stage's checkpoint, or the name of the
    model no stage makes (the random agent)."""
    return str(checkpoint_path(run_dir, model)) if model in STAGES else model


def scored_steps(chosen: Recipe, model: str) -> str:
    """The steps of every stage a model's scores rest on ("xpl 9000, proposal 4000, perception
    4000"): a recipe that trains a stage further, in a later phase added since, is scored again."""
    return ", ".join(f"{stage} {chosen.final_training(stage).steps}" for stage in resting_on(model))


def stage_processes(wanted: int, training: TrainConfig) -> int:
    """The most processes, up to `wanted`, among which a stage's data shards split evenly (any
    number when the stage leaves its shards to the first launch): a recipe that fixes its shards
    then draws the same batches on every machine."""
    shards = training.data_shards
    if not shards:
        return wanted
    return max(count for count in process_counts(shards) if count <= wanted)


def _train_phases(stages: Stages, model: str, train: Callable[[dict], object], phases: tuple[TrainConfig, ...],
                  seed: int) -> None:
    """A model's first training run, then each later phase of its recipe, resumed from the one
    before with the phase's whole training config (the run's seed kept)."""
    stages.run(f"train-{model}", lambda: train({"seed": seed}))
    for number, phase in enumerate(phases, start=2):
        stages.run(f"train-{model}-{number}", lambda phase=phase: train({**to_dict(phase), "seed": seed}))


def _lane(config: PipelineConfig, sizes: Recipe, model: str, threads: int) -> None:
    """One model's training stages in a process of its own with `threads` threads and the
    caller's recipe `sizes` (no progress bars: lanes would draw over each other; each stage's
    start is printed). Scoring is left to the caller: it uses every core well (on one thread
    beside another lane it took twice as long)."""

    RECIPES[config.recipe] = sizes
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)
    _model_stages(config, model, Stages(Path(config.out), config.progress), bars=False, scoring=False)


def _remove(directory: Path, *patterns: str) -> None:
    """Delete what an earlier run of a report stage drew, so that a rerun for fewer models
    leaves no figure of a dropped one (report.md shows every figure in the directory)."""
    for pattern in patterns:
        for path in directory.glob(pattern):
            path.unlink()


def _explanations(run_dir: Path, test_data: Path, models: tuple[str, ...], device: str = "cpu") -> None:
    """The paper's Fig. 7/8 for the first pair of blocking S2 and collision S3, member 0."""

    _remove(run_dir / "report", "explanation-*.png")
    xpl = next((m for m in models if role_of(m) == XPL), None)
    if xpl is None:
        return
    scorer = load_model(scored_reference(run_dir, xpl), device)
    with store.open_dataset(test_data) as file:
        scenario, setting = store.strings(file, "scenario"), store.strings(file, "setting")
        member = file["member"][:]
    for name, want in (("blocking-S2", ("blocking", "S2")), ("collision-S3", ("collision", "S3"))):
        index = next(i for i in range(len(member)) if (scenario[i], setting[i]) == want and member[i] == 0)
        figure = plot_explanation(with_display(explain(scorer, str(test_data), index), test_data, index))
        figure.savefig(run_dir / "report" / f"explanation-{name}.png", dpi=90, bbox_inches="tight")
        plt.close(figure)


def compare_models(rows: list[dict]) -> list[str]:
    """The report's verdict on the baselines, in sentences with the numbers: XPL's explicative
    accuracy against each other model's (the paper: only XPL is above 50% there), the
    predictive accuracy of every model, and whether the random agent sits at chance."""
    def value(model: str, scenario: str, setting: str) -> dict | None:
        return next((r for r in rows if r["metric"] == "comparative" and r["model"] == model
                     and (r["scenario"], r["setting"]) == (scenario, setting)), None)

    models = list(dict.fromkeys(r["model"] for r in rows))
    if len(models) < 2:
        return []
    roles = {model: role_of(model) for model in models}
    xpl = next((m for m in models if roles[m] == XPL), None)
    lines = ["## XPL against the other models", ""]
    for scenario in ("collision", "blocking"):
        ours = value(xpl, scenario, "S3")
        if ours is None:
            continue
        for other in (m for m in models if roles[m] not in (XPL, CHANCE)):
            theirs = value(other, scenario, "S3")
            if theirs is not None:
                gap = 100 * (float(ours["value"]) - float(theirs["value"]))
                verdict = "beats" if gap > 0 else "does not beat"
                lines.append(f"- {scenario} S3 (explicative): XPL {100 * float(ours['value']):.1f}% {verdict} "
                             f"{other} {100 * float(theirs['value']):.1f}% ({gap:+.1f} points).")
    for model in (m for m in models if roles[m] != CHANCE):
        worst = min((r for r in rows if r["metric"] == "comparative" and r["model"] == model
                     and r["setting"] == "S1"), key=lambda r: float(r["value"]), default=None)
        if worst is not None:
            lines.append(f"- {model}: lowest predictive (S1) accuracy {100 * float(worst['value']):.1f}% "
                         f"({worst['scenario']}).")
    for model in (m for m in models if roles[m] == CHANCE):
        chance = [r for r in rows if r["metric"] == "comparative" and r["model"] == model]
        inside = sum(float(r["low"]) <= 0.5 <= float(r["high"]) for r in chance)
        lines.append(f"- {model}: 50% lies inside the 95% interval in {inside} of {len(chance)} settings.")
    return lines


def write_report(run_dir: Path, config: PipelineConfig) -> Path:
    """report.md: the holistic and comparative tables and the figures."""
    rows = list(csv.DictReader(open(run_dir / "report" / "metrics.csv")))
    videos = config.train_videos or recipe(config.recipe).train_videos
    lines = [f"# xvoe pipeline report: {run_dir.name}", "",
             f"Recipe `{config.recipe}`, {videos} training videos, {config.pairs} test pairs per setting, "
             f"seed {config.seed}. Values are percentages with 95% intervals and the pairs they rest on "
             f"(comparative: Wilson's; holistic: the wider of a bootstrap over pairs and Wilson's).", ""]
    models = list(dict.fromkeys(r["model"] for r in rows))
    total = [r for r in rows if r["column"] == "score"]

    def cell(row: dict) -> str:
        return (f"{100 * float(row['value']):.1f} [{100 * float(row['low']):.0f}, {100 * float(row['high']):.0f}]"
                + (f", n = {row['count']}" if row.get("count") else ""))

    lines += ["## Holistic (AUC) per scenario", "", "| scenario | " + " | ".join(models) + " |",
              "|---|" + "---|" * len(models)]
    for scenario in dict.fromkeys(r["scenario"] for r in total if r["metric"] == "holistic"):
        found = {r["model"]: r for r in total if r["metric"] == "holistic" and r["scenario"] == scenario}
        lines.append(f"| {scenario} | " + " | ".join(cell(found[m]) if m in found else "" for m in models) + " |")
    lines += ["", "## Comparative per setting (ideal: S1 100, S2 50, S3 100)", "",
              "| setting | " + " | ".join(models) + " |", "|---|" + "---|" * len(models)]
    keys = dict.fromkeys((r["scenario"], r["setting"]) for r in total if r["metric"] == "comparative")
    for scenario, setting in keys:
        found = {r["model"]: r for r in total
                 if r["metric"] == "comparative" and (r["scenario"], r["setting"]) == (scenario, setting)}
        lines.append(f"| {scenario} {setting} | " + " | ".join(cell(found[m]) if m in found else "" for m in models)
                     + " |")
    lines += ["", *compare_models(total), ""]
    for figure in sorted((run_dir / "report").glob("*.png")):
        lines += [f"![{figure.stem}](report/{figure.name})", ""]
    headers = run_dir / "report" / "headers.json"      # absent from a report made before score files had one
    lines += ["## Score files: what each was made with", ""] if headers.is_file() else []
    for entry in json.loads(headers.read_text()) if headers.is_file() else []:
        lines += [f"`{Path(entry['scores']).name}`:", "", *header_lines(entry["header"]), ""]
    lines += ["## Stage times", "", "| stage | time |", "|---|---|"]
    lines += [f"| {name} | {seconds:.1f} s |" for name, seconds in stage_times(run_dir).items()]
    out = run_dir / "report.md"
    out.write_text("\n".join(lines) + "\n")
    return out
