"""The one training loop every stage of XPL uses.

A stage hands over a `Job`: its model, a function from step to the local batch, and its
config as JSON. The loop owns the rest: the optimiser and learning-rate schedule, the
progress bar, a CSV of losses beside the checkpoint, atomic checkpoints (config, step, model
or its moving average, optimiser and RNG states) every few minutes, exact resumption, and
running under `torchrun --nproc_per_node N` with DistributedDataParallel (gloo on CPU, nccl on
GPU; the process's own setup is `distributed`).

Batches are drawn from generators seeded by (seed, step, shard), so a resumed run repeats
no batch and skips none, and N processes compute the gradient of the same global batch as
one process that holds all the shards.
"""
from __future__ import annotations

import csv
import io
import os
import random
import time
import warnings
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn

from ..errors import XvoeError
from ..models.config import to_dict
from ..models.devices import mixed_precision
from ..outputs import claim_directory, claim_file, claim_scope
from ..progress import progress_bar
from .checkpoints import CHECKPOINT_FORMAT, first_not_finite, load_checkpoint, load_weights, save_checkpoint
from .config import TrainConfig
from .distributed import Dist, StopRequests
from .stages import PERCEPTION, PHYDNET

__all__ = ["Job", "checkpoint_path", "fit", "learning_rate"]


@dataclass
class Job:
    """What a stage gives the loop."""

    stage: str                                    # names the files: STAGE.pt and STAGE.csv
    model: nn.Module                              # forward(batch) returns a dict with "loss"
    batches: Callable[[int], Any]                 # step -> this process's part of the batch
    config: dict                                  # the stage's model config, stored in the checkpoint
    items: Callable[[Any], int] = len             # images (or videos) in a local batch, for throughput
    meta: dict = field(default_factory=dict)      # e.g. the data file, stored in the checkpoint


def learning_rate(config: TrainConfig, step: int) -> float:
    """Linear warm-up, then halving every decay_steps."""
    warm = min(1.0, (step + 1) / max(1, config.warmup_steps))
    return config.lr * warm * 0.5 ** (max(0, step - config.warmup_steps) / config.decay_steps)


def checkpoint_path(run_dir: str | os.PathLike, stage: str) -> Path:
    return Path(run_dir) / f"{stage}.pt"


def _log_path(run_dir: str | os.PathLike, stage: str) -> Path:
    return Path(run_dir) / f"{stage}.csv"


def _rng_state() -> dict:
    """Every generator's state as tensors and plain data, which a checkpoint loads without pickle."""
    kind, key, position, has_gauss, gauss = np.random.get_state()
    return {"python": random.getstate(), "numpy": (kind, torch.from_numpy(key.astype(np.int64)), position,
                                                   has_gauss, gauss),
            "torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def _set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    kind, key, *rest = state["numpy"]         # the key: a tensor, or an array in older checkpoints
    np.random.set_state((kind, np.asarray(key.cpu() if isinstance(key, torch.Tensor) else key, np.uint32), *rest))
    # generator states are CPU byte tensors, wherever the checkpoint was mapped to
    torch.set_rng_state(state["torch"].cpu())
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([part.cpu() for part in state["cuda"]])


class _WeightAverage:
    """An exponential moving average of a model's weights, corrected for its start as Adam's
    moments are: after t steps it weighs step s by decay**(t - s), normalised, so that a short
    run's average is not pulled toward the first weights. The trained weights' noise at the
    last steps (the batch drawn, the learning rate still high) averages out."""

    def __init__(self, model: nn.Module, decay: float):
        self.decay = decay
        sources = model.state_dict()        # views of the parameters, updated in place by the optimiser
        self.state = {name: value.detach().clone() for name, value in sources.items()}
        pairs = [(self.state[name], sources[name]) for name in self.state]
        self.averaged = [average for average, _ in pairs if average.is_floating_point()]
        self.trained = [source for average, source in pairs if average.is_floating_point()]
        self.copied = [(average, source) for average, source in pairs if not average.is_floating_point()]  # counters

    def update(self, step: int) -> None:
        """Take in the weights after `step` steps (1 for the first)."""
        torch._foreach_lerp_(self.averaged, self.trained, (1.0 - self.decay) / (1.0 - self.decay ** step))
        for average, source in self.copied:
            average.copy_(source)

    def load(self, state: dict[str, torch.Tensor]) -> None:
        for name, value in state.items():
            self.state[name].copy_(value)


class _CsvLog:
    """Loss rows beside the checkpoint, one every `every` steps and one where a session ends,
    written with each checkpoint (`data`), so that the two always agree: an interrupted or
    failed session leaves the log of its last checkpoint, never rows that no checkpoint holds.

    On resume, rows after the checkpoint's step and the row of the session's end are dropped,
    so the log reads as if the run had never stopped.
    """

    def __init__(self, path: Path, columns: list[str], resume_step: int | None, every: int):
        self.path, self.columns, self.rows = path, columns, []
        if resume_step is not None and path.exists():
            with open(path, newline="") as handle:
                self.rows = [row for row in csv.DictReader(handle)
                             if int(row["step"]) <= resume_step and int(row["step"]) % every == 0]

    def write(self, row: dict) -> None:
        self.rows.append(row)

    def data(self) -> bytes:
        """The log as a CSV file's bytes."""
        text = io.StringIO(newline="")
        writer = csv.DictWriter(text, self.columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(self.rows)
        return text.getvalue().encode()


class _Meter:
    """Running means of the loss terms between two CSV rows."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.count = 0

    def add(self, values: dict[str, torch.Tensor]) -> None:
        for name, value in values.items():
            self.sums[name] = self.sums.get(name, 0.0) + float(value)
        self.count += 1

    def means(self) -> dict[str, float]:
        return {name: total / max(1, self.count) for name, total in self.sums.items()}

    def take(self) -> dict[str, float]:
        means = self.means()
        self.sums, self.count = {}, 0
        return means


# the stages whose batches are not videos drawn by group, and what they draw instead
_UNFOCUSED = {PERCEPTION: "single frames"}


@claim_scope()
def fit(job: Job, config: TrainConfig, run_dir: str | os.PathLike, *, place: Dist | None = None,
        resume: bool = False, overwrite: bool = False, progress: bool = True) -> Path:
    """Train `job.model` for config.steps steps (or config.max_minutes), checkpointing as it goes.

    Returns the checkpoint path. With `resume`, the model, optimiser, step, RNG states and the
    loss CSV continue from the checkpoint in run_dir, as if the run had never stopped; from a
    shipped checkpoint (weights only), the weights and step do, with a fresh optimiser.
    """
    place = place or Dist()
    _check_job(job, config)
    run_dir = claim_directory(run_dir)
    ckpt = checkpoint_path(run_dir, job.stage)
    if place.main:      # one run trains a stage of a run directory at a time; its other processes follow this one
        claim_file(ckpt, overwrite=True, what=f"the {job.stage} stage's checkpoint")
    if ckpt.exists() and not (resume or overwrite):
        raise XvoeError(f"{ckpt} exists; pass --resume to continue it or --overwrite to start again")
    model = job.model.to(place.device)
    # fused: one kernel of torch's own, where the loop of ops takes the square root from MKL's vector
    # library, whose last bit differs between CPU makers (docs/decisions.md, "One seed, one set of weights")
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr, fused=place.device.type in ("cpu", "cuda"))
    run = _Run(job, config, place, ckpt, _log_path(run_dir, job.stage), model, optimiser, resume)
    if resume and ckpt.exists():
        run.resume()
    wrapped = model
    if place.world > 1:
        wrapped = nn.parallel.DistributedDataParallel(model, device_ids=[place.device] if place.device.type == "cuda"
                                                      else None)
    if place.main:
        run_dir.mkdir(parents=True, exist_ok=True)
    run.begin(progress)
    precision = mixed_precision(place.device)
    step = run.start
    with StopRequests() as stop:
        while step < config.steps and not stop.agreed(place, run.out_of_time()):
            for group in optimiser.param_groups:
                group["lr"] = learning_rate(config, step)
            batch = job.batches(step)       # this process's share: latents (B, T, K, D) and masks, or videos
            run.items += job.items(batch)
            terms = _step(wrapped, optimiser, batch, place.device, precision, config.grad_clip)
            step += 1
            run.after_step(step, terms)
        stop.agreed(place, out_of_time=False)       # a request during the last step stops what follows too
    run.end(step)
    if place.world > 1:
        dist.barrier()
    if stop.asked:
        raise KeyboardInterrupt(f"stopped at step {step}, which {ckpt} holds: resume to go on")
    return ckpt


def _step(wrapped: nn.Module, optimiser: torch.optim.Optimizer, batch: Any, device: torch.device,
          precision: AbstractContextManager, grad_clip: float) -> dict[str, Tensor]:
    """One optimiser step on a local batch: its loss terms, `loss` () the one differentiated."""
    batch = batch.to(device) if hasattr(batch, "to") else batch
    with precision:
        terms = wrapped(batch)                      # {"loss": (), ...}: the objective and its parts
    optimiser.zero_grad(set_to_none=True)
    terms["loss"].backward()
    if grad_clip:
        nn.utils.clip_grad_norm_(wrapped.parameters(), grad_clip)
    optimiser.step()
    return terms


def _check_job(job: Job, config: TrainConfig) -> None:
    """Refuse, before any step, a setting of the config that the stage has not (a config checks
    its own domains, and a batch source the memory its batches need)."""
    if config.airborne_share and job.stage != PERCEPTION:
        raise XvoeError(f"airborne_share picks the perception stage's frames; the {job.stage} stage has none")
    if config.lstm_kernel and job.stage != PHYDNET:
        raise XvoeError(f"lstm_kernel widens PhyDNet's ConvLSTM gates; the {job.stage} stage has none")
    if (config.focus_group or config.focus_share) and job.stage in _UNFOCUSED:
        raise XvoeError(f"focus_group and focus_share pick videos of a group; the {job.stage} stage draws "
                        f"{_UNFOCUSED[job.stage]}")


class _Run:
    """What a session of `fit` keeps beside the model and the optimiser: the step it started
    at, its time, the running means of the loss terms and their CSV log, the weights' moving
    average, the progress bar; and how it writes a checkpoint of them."""

    def __init__(self, job: Job, config: TrainConfig, place: Dist, ckpt: Path, log: Path, model: nn.Module,
                 optimiser: torch.optim.Optimizer, resume: bool):
        self.job, self.config, self.place, self.ckpt, self.log = job, config, place, ckpt, log
        self.model, self.optimiser, self.resumed = model, optimiser, resume
        self.start, self.elapsed, self.meter, self.items = 0, 0.0, _Meter(), 0
        self.average = _WeightAverage(model, config.average_decay) if config.average_decay else None
        self.table: _CsvLog | None = None

    def resume(self) -> None:
        """Continue from the checkpoint: weights, step and time; the optimiser, RNG states and
        running means where it holds them (a shipped checkpoint keeps weights only)."""
        state = load_checkpoint(self.ckpt, self.job.stage, self.place.device)
        load_weights(self.model, state, self.ckpt)      # "model" is checked to fit even where "trained" replaces it
        if "trained" in state:
            load_weights(self.model, state, self.ckpt, "trained")
        if self.average:
            self.average.load(state["model"])
        self.start, self.elapsed = state["step"], state.get("elapsed", 0.0)
        if "optimizer" in state:
            self.optimiser.load_state_dict(state["optimizer"])
            _set_rng_state(state["rng"])
            self.meter.sums, self.meter.count = dict(state["meter"]["sums"]), state["meter"]["count"]
        elif self.place.main:
            # a shipped checkpoint keeps weights only: train it further from its step
            warnings.warn(f"{self.ckpt} holds no optimiser state (a shipped model?): Adam starts afresh at step "
                          f"{self.start}", stacklevel=3)

    def begin(self, progress: bool) -> None:
        """Start the progress bar and the clocks: the session's, and the run's (its time before)."""
        self.bar = progress_bar(total=self.config.steps, initial=self.start, desc=self.job.stage,
                                disable=not (progress and self.place.main), dynamic_ncols=True)
        self.session = self.last_save = time.monotonic()
        self.began = self.session - self.elapsed

    def out_of_time(self) -> bool:
        return bool(self.config.max_minutes) and self.elapsed >= 60 * self.config.max_minutes

    def after_step(self, step: int, terms: dict[str, Tensor]) -> None:
        """Take in the weights and loss terms of `step` steps: the average, the means, a CSV row
        every log_every steps, a checkpoint every checkpoint_minutes."""
        if self.average:
            self.average.update(step)
        self.elapsed = time.monotonic() - self.began
        self.meter.add({name: value.detach() for name, value in terms.items() if value.dim() == 0})
        if step % self.config.log_every == 0:
            self.write_row(step, self.meter.take())
        self.bar.update(1)
        if self.place.main and time.monotonic() - self.last_save >= 60 * self.config.checkpoint_minutes:
            self.save(step)
            self.last_save = time.monotonic()

    def end(self, step: int) -> None:
        """Close the bar, log the steps since the last row and write the last checkpoint."""
        self.bar.close()
        if self.meter.count:
            self.write_row(step, self.meter.means())
        self.save(step)

    def write_row(self, step: int, means: dict[str, float]) -> None:
        rate = self.items * self.place.world / max(1e-9, time.monotonic() - self.session)
        row = {"step": step, "minutes": round(self.elapsed / 60, 4), "lr": learning_rate(self.config, step - 1),
               "items_per_second": round(rate, 1), **{name: round(value, 5) for name, value in means.items()}}
        self.bar.set_postfix({name: f"{value:.4g}" for name, value in means.items() if name in ("loss", "psnr")})
        if self.place.main:
            self.table = self.table or _CsvLog(self.log, list(row), self.start if self.resumed else None,
                                              self.config.log_every)
            self.table.write(row)

    def save(self, step: int) -> None:
        """The checkpoint of `step` steps and the log beside it, from the main process; refused
        where the weights are not finite, so that the last good checkpoint stays as it was."""
        if not self.place.main:
            return
        # "model" is what every loader reads: the average when there is one
        weights = {"model": self.average.state, "trained": self.model.state_dict()} if self.average else \
            {"model": self.model.state_dict()}
        if (bad := first_not_finite(weights)) is not None:
            raise XvoeError(f"the {self.job.stage} stage diverged by step {step} (its weights are not finite: {bad}); "
                            f"nothing was saved: train with a lower --lr than {self.config.lr:g}")
        save_checkpoint(self.ckpt, {"format": CHECKPOINT_FORMAT, "stage": self.job.stage, "config": self.job.config,
                                    "train": to_dict(self.config), "step": step, "elapsed": self.elapsed,
                                    **weights, "optimizer": self.optimiser.state_dict(),
                                    "rng": _rng_state(), "meta": self.job.meta, "world": self.place.world,
                                    "kernels": torch.backends.cpu.get_cpu_capability(),
                                    "meter": {"sums": self.meter.sums, "count": self.meter.count}},
                        beside={self.log: self.table.data()} if self.table else None)
