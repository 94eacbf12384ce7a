"""Scoring and explaining with either definition of surprise, as one call each.

The MSE score and its explanation live in xvoe.evaluation; the NLL's in inference, the layer
above it. These choose between them by name, for the command line, the pipeline, the
notebooks and a user's own script alike. A score reads top to bottom (`score`, then
`_score_split`): the split read and checked, the latents taken once (the split's latent cache),
each batch encoded once and given to each surprise definition asked for (`score_batch`), the
columns reduced from the curves by name, and the two files written together.
"""
from __future__ import annotations

import os
import shutil
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import nullcontext
from dataclasses import replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from xvoe.inference.explain import explain_nll
from xvoe.inference.model import InferenceConfig
from xvoe.inference.score import NLLRun, nll_batch, nll_config, nll_excess, nll_run

from ..domains import TIME_LIMIT
from ..errors import XvoeError
from ..evaluation.checks import check_spread
from ..evaluation.explain import Explanation, explain_drawn
from ..evaluation.explain import explain as explain_mse
from ..evaluation.score_cache import latent_cache
from ..evaluation.score_curves import curve_columns
from ..evaluation.score_headers import new_header
from ..evaluation.score_tables import ScoreTable
from ..evaluation.score_writer import score_lines, write_score_files
from ..evaluation.scorer import (
    EncodedChunk,
    Scorer,
    as_scorer,
    custom_curves,
    encode_videos,
    mse_curves,
    open_test_split,
    own_surprise,
)
from ..evaluation.shards import batch_count, merge_scores, shard_rows
from ..evaluation.surprise import BETTER, EXPLANATIONS
from ..evaluation.user_models import SurpriseModel, check_model, curve_of
from ..fingerprints import split_identity
from ..models.devices import resolve_device
from ..outputs import claim_file, claim_scope, parts_folder, writing
from ..processes import end_with_parent, interrupts_held
from ..progress import progress_bar
from ..resources import check_workers, cores
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE, check_display_size, display_video, hidden_silhouettes
from ..training.latents import open_latents

__all__ = ["SURPRISES", "check_explanation", "explain", "score", "score_batch", "score_columns", "with_display"]

SURPRISES = ("mse", "nll", "both")
LABELS = ("scenario", "setting", "pair", "member", "possible")     # the split's labels a score file repeats


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
    NLL's random draws (each video's from a generator of its own, seeded from it and the video's
    pixels), so that a score file can be reproduced and its spread measured.
    particles and nll_settings change the model's own NLL settings (its recipe's,
    xvoe.models.nll.InferenceConfig: pixel sigma, exposure penalty, pilot...), e.g.
    {"pixel_sigma": 1.0}, to see how each moves the verdicts.
    workers: processes that each score a shard with the cores shared out, then merged: the
    bytes of one run with as many threads as each worker has. On 2 cores the NLL's small
    tensors keep two processes busier than two threads (docs/decisions.md, "Processes and
    threads").
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
    if surprise != "mse":
        nll_config(InferenceConfig(), particles, nll_settings)      # bad settings fail before the model is loaded
    resolve_device(device)      # an absent device too, before any work
    if workers > 1 and shard != (0, 1):
        raise XvoeError("--workers shards the split itself; leave out --shard")
    scorer = as_scorer(model, device)
    nll = nll_run(scorer, particles, seed, nll_settings) if surprise != "mse" else None    # before any work
    if workers > 1:
        return ScoreTable(_score_in_workers(model, scorer, data, out, workers, overwrite, progress, surprise=surprise,
                                            particles=particles, seed=seed, nll_settings=nll_settings, how=how,
                                            videos_per_batch=videos_per_batch, checks=checks, device=device,
                                            cache=cache, time_limit=time_limit))
    return ScoreTable(_score_split(scorer, data, out, nll, "nll" if surprise == "nll" else "score", how=how,
                                   videos_per_batch=videos_per_batch, shard=shard, checks=checks, overwrite=overwrite,
                                   progress=progress, cache=cache, time_limit=time_limit))


@claim_scope()
def _score_split(scorer: Scorer, data: str | Path, out: str | Path, nll: NLLRun | None, score_column: str, *,
                 how: str, videos_per_batch: int, shard: tuple[int, int], checks: bool, overwrite: bool,
                 progress: bool, cache: str | Path | bool, time_limit: float | None) -> Path:
    """One CSV row per test video (part I of N of them with `shard`), and the per-frame curves
    in an .npz beside it with the header (xvoe.evaluation.score_headers). `nll`: the NLL's
    columns beside the MSE's (None: the MSE's alone); `score_column` names the column that is the
    score (score, or nll). The arguments as `score` takes them."""
    _check_scoring(how, time_limit)
    scorer = replace(scorer, time_limit=time_limit)
    with open_test_split(scorer, data) as file:
        # after every check of the input: a refused run leaves nothing behind
        out = claim_file(out, overwrite)
        curves_path = claim_file(out.with_suffix(".curves.npz"), overwrite, what="the curves beside --out")
        first, last = shard_rows(len(file["rgbd"]), videos_per_batch, shard)
        split = split_identity(file)     # the header's, and the cache's key
        # the parts of a sharded run may run at once: each reads a cache, none makes one
        latents = latent_cache(scorer, data, cache, make=shard == (0, 1), progress=progress, identity=split)
        checks = checks and scorer.custom is not None
        if checks:
            check_model(scorer.custom, scorer.time_limit, file, first, last)
        labels = store.labels(file, LABELS)
        header = new_header(scorer, split, data, score_column, how, nll.header() if nll is not None else None)
        with open_latents(latents) if latents is not None else nullcontext() as encoded:
            curves, values = _score_videos(scorer, file, first, last, videos_per_batch, nll, encoded, progress)
        size = file["rgbd"].shape[2]
    columns = score_columns(scorer, curves, values, how, score_column, nll, size)
    if checks:
        check_spread(columns["score"], scorer.name)
    stored, header = _stored_curves(scorer, curves, header)
    write_score_files(out, curves_path, score_lines(scorer.name, labels, first, columns), header, stored)
    return out


def _check_scoring(how: str, time_limit: float | None) -> None:
    if how not in ("sum", "max"):
        raise XvoeError(f"--aggregate must be sum or max, not {how!r}")
    if time_limit is not None and not time_limit > 0:
        raise XvoeError(f"--time-limit must be a number of seconds above 0, not {time_limit}")


def _score_videos(scorer: Scorer, file: h5py.File, first: int, last: int, videos_per_batch: int,
                  nll: NLLRun | None, latents: h5py.File | None,
                  progress: bool) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """`score_batch` of videos [first, last), batch by batch, joined: the curves (N, T) and values (N,) by name."""
    found = []
    with progress_bar(total=last - first, desc=f"score {scorer.name}", unit="video", disable=not progress) as bar:
        for start in range(first, last, videos_per_batch):
            stop = min(last, start + videos_per_batch)
            found.append(score_batch(scorer, file, start, stop, nll, latents))
            bar.update(stop - start)
    curves, values = zip(*found)
    return ({name: np.concatenate([batch[name] for batch in curves]) for name in curves[0]},
            {name: np.concatenate([batch[name] for batch in values]) for name in values[0]})


def score_batch(scorer: Scorer, file: h5py.File, start: int, stop: int, nll: NLLRun | None = None,
                latents: h5py.File | None = None) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Videos [start, stop) of an open test split scored by every surprise definition asked for:
    their per-frame curves (B, T) and per-video values (B,), by name. A model answering
    `surprise(videos)` gives one term, checked (`custom_curves`); XPL and PLATO give
    the MSE's terms (xvoe.evaluation.scorer, `mse_curves`), and with `nll` the NLL's columns and
    curve (xvoe.inference.score, `nll_batch`), from one encoding of the batch and one drawing of
    its scene. `latents`: the split's open latent cache, read instead of encoding."""
    if scorer.custom is not None:
        return custom_curves(scorer, file, start, stop), {}
    batch = encode_videos(scorer, file, start, stop, latents)      # once, for every definition
    found, scene = mse_curves(scorer, batch)
    curves = {name: curve.cpu().numpy().astype(np.float64) for name, curve in found.items()}
    if nll is None:
        return curves, {}
    values, nll_curves = nll_batch(scorer, batch, nll, scene)
    return curves | nll_curves, values


def score_columns(scorer: Scorer, curves: dict[str, np.ndarray], values: dict[str, np.ndarray], how: str,
                  score_column: str = "score", nll: NLLRun | None = None, size: int = 0) -> dict[str, np.ndarray]:
    """The numeric columns of a score file after its labels, per video, by name, from the curves
    and values of `score_batch`: score, s_img, s_dyn, paper_score, then s_rec and excess for a
    model with a perception module (`curve_columns`), then the NLL's (nll, ess, p_hidden, p_two
    and nll_excess, for frames of `size` pixels a side); a model of your own's score alone.
    `score_column` is copied into score."""
    if own_surprise(scorer):
        return {"score": curve_columns(curves, how, own=curve_of(scorer.custom)[0])["score"]}
    columns = curve_columns(curves, how) | values
    if nll is not None:
        columns["nll_excess"] = nll_excess(values["nll"], curves["s_rec"], size, nll)
    columns["score"] = columns[score_column]
    return columns


def _stored_curves(scorer: Scorer, curves: dict[str, np.ndarray], header: dict) -> tuple[dict[str, np.ndarray], dict]:
    """The curves a score file keeps, and its header with the name and axis of a model's own curve:
    a model answering `surprise(videos)` keeps its one term under its own name (`curve_of`)."""
    if scorer.custom is None:
        return curves, header
    own, label = curve_of(scorer.custom)
    return {own: curves[own]}, header | {"curve": own, "curve_label": label}


def check_explanation(explanation: str) -> None:
    """A one-line refusal of an MSE explanation that is not one of EXPLANATIONS."""
    if explanation not in EXPLANATIONS:
        raise XvoeError(f"--explanation must be {' or '.join(EXPLANATIONS)}, not {explanation!r}")


# parts a worker takes in turn: the settings of a split differ in cost (the NLL's full runs gather in
# some), so halves by order left one worker idle for a sixth of the run
PARTS_PER_WORKER = 4


@claim_scope()
def _score_in_workers(model: str | Scorer, scorer: Scorer, data: str | Path, out: str | Path, workers: int,
                      overwrite: bool, progress: bool, **settings) -> Path:
    """`score` of `model` (loaded here as `scorer`) in `workers` spawned processes, the split cut
    into up to PARTS_PER_WORKER parts a worker (whole batches), each handed to the next worker
    free, merged into `out`; the progress bar here counts the videos of the parts done. The
    split's latent cache is made here first, for all of them to read. The parts are written in a
    folder beside `out` named by this process (`parts_folder`), which a later run to `out`
    removes if this one was killed before it could."""
    out = claim_file(out, overwrite)      # refused before any work, as one run would be
    with open_test_split(scorer, data) as file:      # checked, and its latent cache made, before any worker starts
        count = len(file["rgbd"])
        settings["cache"] = latent_cache(scorer, data, settings["cache"], progress=progress) or False
    batch = settings["videos_per_batch"]
    shards = min(workers * PARTS_PER_WORKER, batch_count(count, batch))
    threads = max(1, cores() // workers)
    parts_dir = parts_folder(out)
    parts_dir.mkdir()
    try:
        parts = [parts_dir / f"part{index}.csv" for index in range(shards)]
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_worker_threads,
                                 initargs=(threads, os.getpid())) as pool:
            with interrupts_held():     # a submit may start a worker
                running = {pool.submit(_score_part, out, model, data, part, shard=(index, shards), progress=False,
                                       **settings): index for index, part in enumerate(parts)}
            with progress_bar(total=count, desc=f"score {scorer.name}", unit="video", disable=not progress) as bar:
                for done in as_completed(running):
                    done.result()
                    first, last = shard_rows(count, batch, (running[done], shards))
                    bar.update(last - first)
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
            particles: int | None = None, seed: int = 0, explanation: str = BETTER,
            display_size: int | None = DISPLAY_SIZE, device: str = "cpu",
            chunk: EncodedChunk | None = None) -> Explanation:
    """What the model believes is behind the wall in video `index`: Transformer 2's proposal
    (surprise "mse"; with explanation "better", the default verdict's, only where it explains the
    video better than nothing hidden; "proposal", always, as the paper) or the Pyro model's
    posterior (surprise "nll", by the model's NLL method (sequential Monte Carlo over frames
    unless its settings say "importance") with `particles` particles drawn from `seed`; None: the
    model's setting). With the video's scene at `display_size` for `plot_explanation` to draw
    the explanation onto (None: the model's frames alone); the model reads its own frames.
    device: where a model given by name runs. chunk: the video's latent cache chunk already
    encoded by this model (`xvoe.evaluation.scorer.encode_chunk`), for a caller that explains
    many videos to encode each chunk once; the explanation is the same."""
    check_explanation(explanation)
    if display_size is not None:
        check_display_size(display_size)
    scorer = as_scorer(model, device)
    return with_display(_explain(scorer, data, index, surprise, particles, seed, explanation, chunk), data, index,
                        display_size)


def _explain(scorer: Scorer, data: str | Path, index: int, surprise: str, particles: int | None, seed: int,
             explanation: str, chunk: EncodedChunk | None = None) -> Explanation:
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
        return explain_nll(scorer, str(data), index, particles=particles, seed=seed, chunk=chunk)
    if surprise != "mse":
        raise XvoeError(f"--surprise must be mse or nll, not {surprise!r}")
    return explain_mse(scorer, str(data), index, chunk)


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
