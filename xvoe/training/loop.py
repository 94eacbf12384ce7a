"""The one training loop every stage of XPL uses.

A stage hands over a `Job`: its model, a function from step to the local batch, and its
config as JSON. The loop owns the rest: the optimiser and learning-rate schedule, the
progress bar, a CSV of losses beside the checkpoint, atomic checkpoints (config, step, model
or its moving average, optimiser and RNG states) every few minutes, exact resumption, and
running under `torchrun --nproc_per_node N` with DistributedDataParallel (gloo on CPU, nccl on GPU).

Batches are drawn from generators seeded by (seed, step, shard), so a resumed run repeats
no batch and skips none, and N processes compute the gradient of the same global batch as
one process that holds all the shards.
"""
from __future__ import annotations

import csv
import io
import os
import random
import signal
import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from ..domains import check_config
from ..errors import XvoeError
from ..models.config import override, to_dict
from ..models.devices import mixed_precision, resolve_device
from ..outputs import claim_directory, claim_file, claim_scope
from ..progress import progress_bar
from ..resources import check_memory, cores
from .checkpoints import CHECKPOINT_FORMAT, first_not_finite, load_checkpoint, load_weights, save_checkpoint
from .config import TrainConfig


@dataclass
class Job:
    """What a stage gives the loop."""

    stage: str                                    # names the files: STAGE.pt and STAGE.csv
    model: nn.Module                              # forward(batch) returns a dict with "loss"
    batches: Callable[[int], Any]                 # step -> this process's part of the batch
    config: dict                                  # the stage's model config, stored in the checkpoint
    items: Callable[[Any], int] = len             # images (or videos) in a local batch, for throughput
    meta: dict = field(default_factory=dict)      # e.g. the data file, stored in the checkpoint
    item_bytes: int = 0                           # bytes of one item of a batch as the model reads it (0: unknown)


@dataclass
class Dist:
    """Where this process sits in a torchrun launch (rank 0 of 1 when run alone)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def main(self) -> bool:
        return self.rank == 0


def setup_distributed(device: str | torch.device = "cpu") -> Dist:
    """Join the process group torchrun set up, if any, on `device`; "cuda" without a number is
    each process's own GPU (its local rank's)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local_rank = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    chosen = resolve_device(device)
    cuda = chosen.type == "cuda"
    if cuda:
        chosen = torch.device("cuda", local_rank if chosen.index is None else chosen.index)
        torch.cuda.set_device(chosen)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    return Dist(rank, world, local_rank, chosen)


def set_threads(config: TrainConfig, local_world: int) -> None:
    """Share the cores between the processes of this machine: config.threads, else
    OMP_NUM_THREADS when set (torchrun sets it), else the cores divided by the processes."""
    threads = config.threads or int(os.environ.get("OMP_NUM_THREADS", "0") or 0)
    torch.set_num_threads(threads or max(1, cores() // max(1, local_world)))


def learning_rate(config: TrainConfig, step: int) -> float:
    """Linear warm-up, then halving every decay_steps."""
    warm = min(1.0, (step + 1) / max(1, config.warmup_steps))
    return config.lr * warm * 0.5 ** (max(0, step - config.warmup_steps) / config.decay_steps)


def checkpoint_path(run_dir: str | os.PathLike, stage: str) -> Path:
    return Path(run_dir) / f"{stage}.pt"


def log_path(run_dir: str | os.PathLike, stage: str) -> Path:
    return Path(run_dir) / f"{stage}.csv"


def rng_state() -> dict:
    """Every generator's state as tensors and plain data, which a checkpoint loads without pickle."""
    kind, key, position, has_gauss, gauss = np.random.get_state()
    return {"python": random.getstate(), "numpy": (kind, torch.from_numpy(key.astype(np.int64)), position,
                                                   has_gauss, gauss),
            "torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    kind, key, *rest = state["numpy"]         # the key: a tensor, or an array in older checkpoints
    np.random.set_state((kind, np.asarray(key.cpu() if isinstance(key, torch.Tensor) else key, np.uint32), *rest))
    # generator states are CPU byte tensors, wherever the checkpoint was mapped to
    torch.set_rng_state(state["torch"].cpu())
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([part.cpu() for part in state["cuda"]])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


# The code paths of torch's own kernels and oneDNN's convolutions: AVX2, which both machine kinds have,
# so that they sum alike on either (docs/decisions.md, "One seed, one set of weights"; MKL's matrix
# products still follow the CPU's maker). An environment that names its own keeps it.
KERNELS = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2"}


def pin_kernels() -> str:
    """Ask for the `KERNELS` instruction set and say which this process's torch kernels use.
    Torch reads it at its first kernel, so a process that ran one before keeps what it chose
    (a checkpoint records it: `kernels`); a training command or a stage's process runs none
    before this."""
    for name, value in KERNELS.items():
        os.environ.setdefault(name, value)
    return torch.backends.cpu.get_cpu_capability()


def start_process(config: TrainConfig, place: Dist) -> TrainConfig:
    """A stage's config in this process, as one process or any number of them read it: the
    kernels pinned, one data shard per process unless set, this process's share of the cores
    taken (unless the config fixes its threads), every RNG seeded."""
    pin_kernels()
    config = override(config, data_shards=config.data_shards or place.world)
    set_threads(config, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))
    seed_everything(config.seed)
    return config


class WeightAverage:
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


class CsvLog:
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
UNFOCUSED = {"perception": "single frames"}


@claim_scope()
def fit(job: Job, config: TrainConfig, run_dir: str | os.PathLike, *, place: Dist | None = None,
        resume: bool = False, overwrite: bool = False, progress: bool = True) -> Path:
    """Train `job.model` for config.steps steps (or config.max_minutes), checkpointing as it goes.

    Returns the checkpoint path. With `resume`, the model, optimiser, step, RNG states and the
    loss CSV continue from the checkpoint in run_dir, as if the run had never stopped; from a
    shipped checkpoint (weights only), the weights and step do, with a fresh optimiser.
    """
    place = place or Dist()
    check_config(config)        # a config built in Python, not through override, is checked too
    # a batch's float copy for the model, at the least: a size past the machine is named before any step
    check_memory(job.item_bytes * config.batch_size, f"--batch-size {config.batch_size}")
    if config.airborne_share and job.stage != "perception":
        raise XvoeError(f"airborne_share picks the perception stage's frames; the {job.stage} stage has none")
    if config.lstm_kernel and job.stage != "phydnet":
        raise XvoeError(f"lstm_kernel widens PhyDNet's ConvLSTM gates; the {job.stage} stage has none")
    if (config.focus_group or config.focus_share) and job.stage in UNFOCUSED:
        raise XvoeError(f"focus_group and focus_share pick videos of a group; the {job.stage} stage draws "
                        f"{UNFOCUSED[job.stage]}")
    run_dir = claim_directory(run_dir)
    ckpt, log = checkpoint_path(run_dir, job.stage), log_path(run_dir, job.stage)
    if place.main:      # one run trains a stage of a run directory at a time; its other processes follow this one
        claim_file(ckpt, overwrite=True, what=f"the {job.stage} stage's checkpoint")
    if ckpt.exists() and not (resume or overwrite):
        raise XvoeError(f"{ckpt} exists; pass --resume to continue it or --overwrite to start again")
    model = job.model.to(place.device)
    # fused: one kernel of torch's own, where the loop of ops takes the square root from MKL's vector
    # library, whose last bit differs between CPU makers (docs/decisions.md, "One seed, one set of weights")
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr, fused=place.device.type in ("cpu", "cuda"))
    start, elapsed, meter = 0, 0.0, _Meter()
    average = WeightAverage(model, config.average_decay) if config.average_decay else None
    if resume and ckpt.exists():
        state = load_checkpoint(ckpt, job.stage, place.device)
        load_weights(model, state, ckpt)        # "model" is checked to fit even where "trained" replaces it
        if "trained" in state:
            load_weights(model, state, ckpt, "trained")
        if average:
            average.load(state["model"])
        start, elapsed = state["step"], state.get("elapsed", 0.0)
        if "optimizer" in state:
            optimiser.load_state_dict(state["optimizer"])
            set_rng_state(state["rng"])
            meter.sums, meter.count = dict(state["meter"]["sums"]), state["meter"]["count"]
        elif place.main:
            # a shipped checkpoint keeps weights only: train it further from its step
            warnings.warn(f"{ckpt} holds no optimiser state (a shipped model?): Adam starts afresh at step "
                          f"{start}", stacklevel=2)
    wrapped = model
    if place.world > 1:
        wrapped = nn.parallel.DistributedDataParallel(model, device_ids=[place.device] if place.device.type == "cuda"
                                                      else None)
    if place.main:
        run_dir.mkdir(parents=True, exist_ok=True)

    def log_row(table: CsvLog | None, step: int, means: dict[str, float]) -> CsvLog | None:
        rate = items * place.world / max(1e-9, time.monotonic() - session)
        row = {"step": step, "minutes": round(elapsed / 60, 4), "lr": learning_rate(config, step - 1),
               "items_per_second": round(rate, 1), **{name: round(value, 5) for name, value in means.items()}}
        bar.set_postfix({name: f"{value:.4g}" for name, value in means.items() if name in ("loss", "psnr")})
        if place.main:
            table = table or CsvLog(log, list(row), start if resume else None, config.log_every)
            table.write(row)
        return table

    def checkpoint(step: int) -> None:
        if place.main:
            # "model" is what every loader reads: the average when there is one
            weights = {"model": average.state, "trained": model.state_dict()} if average else \
                {"model": model.state_dict()}
            if (bad := first_not_finite(weights)) is not None:     # the last good checkpoint stays as it was
                raise XvoeError(f"the {job.stage} stage diverged by step {step} (its weights are not finite: {bad}); "
                                f"nothing was saved: train with a lower --lr than {config.lr:g}")
            save_checkpoint(ckpt, {"format": CHECKPOINT_FORMAT, "stage": job.stage, "config": job.config,
                                   "train": to_dict(config), "step": step, "elapsed": elapsed,
                                   **weights, "optimizer": optimiser.state_dict(),
                                   "rng": rng_state(), "meta": job.meta, "world": place.world,
                                   "kernels": torch.backends.cpu.get_cpu_capability(),
                                   "meter": {"sums": meter.sums, "count": meter.count}},
                            beside={log: table.data()} if table else None)

    table = None
    precision = mixed_precision(place.device)
    bar = progress_bar(total=config.steps, initial=start, desc=job.stage, disable=not (progress and place.main),
               dynamic_ncols=True)
    session = last_save = time.monotonic()
    items, began = 0, session - elapsed
    step = start
    with StopRequests() as stop:
        while step < config.steps and not stop.agreed(place, bool(config.max_minutes)
                                                      and elapsed >= 60 * config.max_minutes):
            for group in optimiser.param_groups:
                group["lr"] = learning_rate(config, step)
            batch = job.batches(step)
            items += job.items(batch)
            batch = batch.to(place.device) if hasattr(batch, "to") else batch
            with precision:
                terms = wrapped(batch)
            optimiser.zero_grad(set_to_none=True)
            terms["loss"].backward()
            if config.grad_clip:
                nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimiser.step()
            step += 1
            if average:
                average.update(step)
            elapsed = time.monotonic() - began
            meter.add({name: value.detach() for name, value in terms.items() if value.dim() == 0})
            if step % config.log_every == 0:
                table = log_row(table, step, meter.take())
            bar.update(1)
            if place.main and time.monotonic() - last_save >= 60 * config.checkpoint_minutes:
                checkpoint(step)
                last_save = time.monotonic()
        stop.agreed(place, out_of_time=False)       # a request during the last step stops what follows too
    bar.close()
    if meter.count:
        table = log_row(table, step, meter.means())
    checkpoint(step)
    if place.world > 1:
        dist.barrier()
    if stop.asked:
        raise KeyboardInterrupt(f"stopped at step {step}, which {ckpt} holds: resume to go on")
    return ckpt


class StopRequests:
    """In the main thread, Ctrl-C (or a Jupyter interrupt) and SIGTERM ask the loop to stop after
    the step it is in, so that the last checkpoint holds that step and a resumed run goes on
    exactly; a second request stops at once. Under torchrun the processes agree before each step
    (a request or a time limit reached in one process stops them all there), so no process waits
    in a gradient exchange that the others have left."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.requested = False      # a request this process got (the handler sets it)
        self.asked = False          # a request every process has agreed on
        self.previous: dict[int, Any] = {}

    def __enter__(self) -> StopRequests:
        if self.enabled:
            self.previous = {number: signal.signal(number, self.ask) for number in (signal.SIGINT, signal.SIGTERM)}
        return self

    def agreed(self, place: Dist, out_of_time: bool) -> bool:
        """Whether every process stops before the next step; `asked` then says whether a request
        (in any process) made it stop."""
        requested = self.requested
        if place.world > 1:
            # a request that lands while the exchange waits is kept for the next step, never lost
            flags = torch.tensor([float(requested), float(out_of_time)], device=place.device)
            dist.all_reduce(flags, op=dist.ReduceOp.MAX)
            requested, out_of_time = bool(flags[0]), bool(flags[1])
        self.asked = requested
        return requested or out_of_time

    def ask(self, number: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc: Any) -> None:
        for number, handler in self.previous.items():
            signal.signal(number, handler)


# --- the perception stage -------------------------------------------------------------
