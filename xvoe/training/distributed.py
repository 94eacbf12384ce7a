"""A training process: where it sits in a torchrun launch, its share of the cores, its kernels,
its seeds, and the stop requests every process of a launch agrees on.

Alone, a process is rank 0 of 1; under `torchrun --nproc_per_node N` the processes join one
process group (gloo on CPU, nccl on GPU) and agree before each step whether to stop, so that no
process waits in a gradient exchange the others have left.
"""
from __future__ import annotations

import atexit
import os
import random
import signal
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.distributed as dist

from ..models.config import override
from ..models.devices import resolve_device
from ..resources import cores
from .config import TrainConfig

__all__ = ["KERNELS", "Dist", "StopRequests", "pin_kernels", "seed_everything", "setup_distributed", "start_process"]

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
        atexit.register(_leave_group)
    return Dist(rank, world, local_rank, chosen)


def _leave_group() -> None:
    """Left for the interpreter's own teardown, gloo's threads abort the process as it exits
    ("terminate called without an active exception"), in about a third of torchrun launches."""
    if dist.is_initialized():
        dist.destroy_process_group()


def _set_threads(config: TrainConfig, local_world: int) -> None:
    """Share the cores between the processes of this machine: config.threads, else
    OMP_NUM_THREADS when set (torchrun sets it), else the cores divided by the processes."""
    threads = config.threads or int(os.environ.get("OMP_NUM_THREADS", "0") or 0)
    torch.set_num_threads(threads or max(1, cores() // max(1, local_world)))


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
    _set_threads(config, int(os.environ.get("LOCAL_WORLD_SIZE", "1")))
    seed_everything(config.seed)
    return config


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
