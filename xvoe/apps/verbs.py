"""Scoring and explaining with either definition of surprise, as one call each.

The MSE score and its explanation live in xvoe.evaluation; the NLL's in inference, the layer
above it. These choose between them by name, for the command line, the pipeline, the
notebooks and a user's own script alike.
"""
from __future__ import annotations

import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import torch

from xvoe.inference.explain import explain_nll
from xvoe.inference.score import NLLColumns

from ..domains import TIME_LIMIT
from ..errors import XvoeError
from ..evaluation.explain import Explanation, explain_drawn
from ..evaluation.explain import explain as explain_mse
from ..evaluation.score import Scorer, SurpriseModel, as_scorer, merge_scores, prepare_latents, score_split
from ..evaluation.score_tables import ScoreTable
from ..evaluation.surprise import EXPLANATIONS
from ..models.devices import resolve_device
from ..outputs import claim_file, claim_scope, parts_folder, writing
from ..processes import end_with_parent, interrupts_held
from ..resources import check_workers, cores
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE, check_display_size, display_video, hidden_silhouettes

SURPRISES = ("mse", "nll", "both")


def score(model: str | Scorer | SurpriseModel, data: str | Path, out: str | Path, *, surprise: str = "mse",
          particles: int | None = None, seed: int = 0, nll_settings: dict[str, Any] | None = None, how: str = "sum",
          videos_per_batch: int = 16, shard: tuple[int, int] = (0, 1), workers: int = 1, checks: bool = True,
          overwrite: bool = False, progress: bool = True, device: str = "cpu",
          cache: str | Path | bool = True, time_limit: float | None = TIME_LIMIT) -> ScoreTable:
    """Score every video of a test split into a CSV (and the per-frame curves beside it); the
    scores as a `ScoreTable`, which keeps the CSV's path (and is taken wherever a path is).

    surprise: "mse", the MSE score (the columns score, s_img and s_dyn hold the default verdict,
    the better of Transformer 2's proposal and nothing hidden; paper_score the paper's, always
    the proposal); "nll", -log p(video) under the Pyro model (the score
    column is the NLL; the columns nll, ess, p_hidden, p_two and nll_excess are added); "both", the
    MSE score with the NLL's columns beside it. shard: (I, N) scores part I of N, for
    `merge_scores` to join (xvoe score --shard / --merge). model: a name (`xpl`, `random`, ...), a run
    directory, a checkpoint, a loaded `Scorer`, or an object of your own with a `name` and a
    `surprise(videos)` method (`xvoe.SurpriseModel`; its other attributes optional). seed: the
    NLL's random draws (each video's from a generator of its own), so that a score file can be
    reproduced and its spread measured.
    particles and nll_settings change the model's own NLL settings (its recipe's,
    xvoe.models.nll.InferenceConfig: pixel sigma, exposure penalty, pilot...), e.g.
    {"pixel_sigma": 1.0}, to see how each moves the verdicts.
    workers: processes that each score a shard with the cores shared out, then merged: the
    bytes of one run with as many threads as each worker has. On 2 cores the NLL's small
    tensors keep two processes busier than two threads (docs/decisions.md, "Scoring in worker
    processes").
    checks: a model answering `surprise(videos)` (a model of your own, PhyDNet, random) passes
    the harness of xvoe.evaluation.checks before its scores are written; False skips all but
    the finite check (docs/evaluate-your-model.md, "4. The checks"). device: where a model given
    by name runs (cpu, cuda, cuda:N, mps; a loaded `Scorer` runs where it was loaded).
    cache: the split's latent cache, which a model with a perception module reads instead of
    encoding the frames, made on first use: True, beside the split (DATA.latents-PERCEPTION.h5,
    one per perception module, shared by every model and surprise definition that reads it); a
    path; False, none. Scores are the same with it or without. time_limit: seconds a model answering
    `surprise(videos)` may take for one batch before the run ends in one line (None: no limit)."""
    if surprise not in SURPRISES:
        raise XvoeError(f"--surprise must be mse, nll or both, not {surprise!r}")
    if workers < 1:
        raise XvoeError(f"--workers must be at least 1, not {workers}")
    check_workers(workers)
    extra = NLLColumns(particles, seed, nll_settings) if surprise != "mse" else None   # bad settings fail here
    resolve_device(device)      # an absent device too, before any work
    if workers > 1 and shard != (0, 1):
        raise XvoeError("--workers shards the split itself; leave out --shard")
    scorer = as_scorer(model, device)
    if workers > 1:
        if extra is not None:
            extra.check(scorer)     # before the cache is made for the workers
        return ScoreTable(_score_in_workers(model, scorer, data, out, workers, overwrite, progress, surprise=surprise,
                                            particles=particles, seed=seed, nll_settings=nll_settings, how=how,
                                            videos_per_batch=videos_per_batch, checks=checks, device=device,
                                            cache=cache, time_limit=time_limit))
    return ScoreTable(score_split(scorer, str(data), str(out), how=how, videos_per_batch=videos_per_batch, extra=extra,
                                  score_column="nll" if surprise == "nll" else "score", shard=shard, checks=checks,
                                  overwrite=overwrite, progress=progress, cache=cache, time_limit=time_limit))


def check_explanation(explanation: str) -> None:
    """A one-line refusal of an MSE explanation that is not one of EXPLANATIONS."""
    if explanation not in EXPLANATIONS:
        raise XvoeError(f"--explanation must be {' or '.join(EXPLANATIONS)}, not {explanation!r}")


@claim_scope()
def _score_in_workers(model: str | Scorer, scorer: Scorer, data: str | Path, out: str | Path, workers: int,
                      overwrite: bool, progress: bool, **settings) -> Path:
    """`score` of `model` (loaded here as `scorer`) in `workers` spawned processes, shard I in
    process I, merged into `out`. The first process draws its progress bar (the shards are of
    one size); the split's latent cache is made here first, for all of them to read. The parts
    are written in a folder beside `out` named by this process (`parts_folder`), which a later
    run to `out` removes if this one was killed before it could."""
    out = claim_file(out, overwrite)      # refused before any work, as one run would be
    settings["cache"] = prepare_latents(scorer, data, settings["cache"], progress=progress) or False
    threads = max(1, cores() // workers)
    parts_dir = parts_folder(out)
    parts_dir.mkdir()
    try:
        parts = [parts_dir / f"part{index}.csv" for index in range(workers)]
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_worker_threads,
                                 initargs=(threads, os.getpid())) as pool:
            with interrupts_held():     # each submit starts a worker
                running = [pool.submit(_score_part, out, model, data, part, shard=(index, workers),
                                       progress=progress and index == 0, **settings)
                           for index, part in enumerate(parts)]
            for done in running:
                done.result()
        return merge_scores(parts, out, overwrite=overwrite)
    finally:
        shutil.rmtree(parts_dir, ignore_errors=True)


def _score_part(out: Path, *args, **kwargs) -> Path:
    """A worker's `score` of its shard: a full disk is named by the output the parts join into."""
    with writing(out):
        return score(*args, **kwargs)


def _worker_threads(threads: int, parent: int) -> None:
    end_with_parent(parent)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)


def explain(model: str | Scorer | SurpriseModel, data: str | Path, index: int, *, surprise: str = "mse",
            particles: int | None = None, seed: int = 0, explanation: str = "better",
            display_size: int | None = DISPLAY_SIZE, device: str = "cpu") -> Explanation:
    """What the model believes is behind the wall in video `index`: Transformer 2's proposal
    (surprise "mse"; with explanation "better", the default verdict's, only where it explains the
    video better than nothing hidden; "proposal", always, as the paper) or the Pyro model's
    posterior (surprise "nll", from `particles` importance samples drawn from `seed`; None: the
    model's setting). With the video's scene at `display_size` for `plot_explanation` to draw
    the explanation onto (None: the model's frames alone); the model reads its own frames.
    device: where a model given by name runs."""
    check_explanation(explanation)
    if display_size is not None:
        check_display_size(display_size)
    scorer = as_scorer(model, device)
    return with_display(_explain(scorer, data, index, surprise, particles, seed, explanation), data, index,
                        display_size)


def _explain(scorer: Scorer, data: str | Path, index: int, surprise: str, particles: int | None, seed: int,
             explanation: str) -> Explanation:
    """The explanation `explain` asked for, of the model's own frames."""
    scorer = replace(scorer, explanation=explanation) if scorer.custom is None else scorer
    if scorer.is_random:
        raise XvoeError("the random agent explains nothing; give a trained model")
    if scorer.phydnet is not None:
        raise XvoeError("PhyDNet predicts pixels and has no hidden object to draw; give an XPL run")
    if scorer.custom is not None:
        if not callable(getattr(scorer.custom, "explain", None)):
            raise XvoeError(f"the model {scorer.name} gives surprise only, no explanation to draw (it has no explain)")
        if surprise != "mse":
            raise XvoeError(f"the model {scorer.name} draws its own explanation; leave out --surprise nll")
        return explain_drawn(scorer, str(data), index)
    if surprise == "nll":
        return explain_nll(scorer, str(data), index, particles=particles, seed=seed)
    if surprise != "mse":
        raise XvoeError(f"--surprise must be mse or nll, not {surprise!r}")
    return explain_mse(scorer, str(data), index)


def with_display(explanation: Explanation, data: str | Path, index: int,
                 display_size: int | None = DISPLAY_SIZE) -> Explanation:
    """The explanation of video `index` of split `data` with that video's scene at
    `display_size` and where its never-seen objects stand there, for `plot_explanation`
    (None: the explanation as it is)."""
    if display_size is None:
        return explanation
    with store.open_dataset(data) as file:
        display = display_video(file, index, display_size)
        return replace(explanation, display=display.rgbd, true_hidden=hidden_silhouettes(file, index, display),
                       display_resimulated=display.resimulated)
