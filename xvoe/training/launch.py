"""A training stage in one process per core, from Python: what `torchrun --standalone` does.

On a small CPU, one-thread processes that share a batch through DistributedDataParallel
train faster than one process with as many threads: the models' layers are too small to
keep a second thread busy (docs/decisions.md, "Processes and threads").
"""
from __future__ import annotations

import os
import signal
from collections.abc import Callable
from typing import Any

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from ..errors import XvoeError
from ..processes import end_with_parent, interrupts_held
from .distributed import StopRequests
from .recipes import RECIPES, Recipe

__all__ = ["rendezvous_store", "on_cores", "ForwardedStops", "Stopped"]

# how long the other processes get to end on their own once one has ended with an error or a stop
GRACE_SECONDS = 60.0


def rendezvous_store() -> dist.TCPStore:
    """The processes' meeting point, on a port the OS chose and held from before they start
    until they end: a port found free and let go could be taken by another run in between
    (torchrun's own agent does the same; the processes join as clients)."""
    return dist.TCPStore("127.0.0.1", 0, is_master=True, wait_for_workers=False)


def on_cores(train: Callable[..., Any], processes: int, recipe: Recipe | None = None, **kwargs: Any) -> None:
    """Run `train(**kwargs)` (a training function of xvoe.training that works under torchrun)
    in `processes` processes of one thread each; with one, in this process as it stands.
    `recipe` is registered under its name in each process, so that a recipe made or changed
    in this one (a test's tiny one) is the one the stage reads."""
    if processes < 1:
        raise ValueError(f"processes must be at least 1, not {processes}")
    if processes == 1:
        train(**kwargs)
        return
    store = rendezvous_store()     # kept in a name until the processes are joined: freed, it lets its port go
    # a Ctrl-C while they start (each imports torch again) is held, here and in them, until the
    # forwarding is in place: it then stops them as one that comes later does
    with ForwardedStops([]) as stops:
        with interrupts_held(workers=True):
            context = mp.start_processes(_process, args=(processes, store.port, train, recipe, kwargs, os.getpid()),
                                         nprocs=processes, join=False, start_method="spawn")
            stops.processes = context.processes
        _join(context)


def _join(context: mp.ProcessContext) -> None:
    """Wait for every process, and raise as one process would where one failed. The others get
    a grace period to end on their own (a stop ends them all, one a little after another) before
    torch ends them."""
    try:
        while not context.join(grace_period=GRACE_SECONDS):
            pass
    except mp.ProcessRaisedException as error:
        raise _as_in_one_process(str(error)) from None
    except mp.ProcessExitedException as error:
        if error.signal_name in ("SIGINT", "SIGTERM"):
            raise KeyboardInterrupt(f"training process {error.error_index} stopped by {error.signal_name}") from None
        raise XvoeError(f"a training process ended before its stage did: {error}") from None


class ForwardedStops(StopRequests):
    """Ctrl-C or SIGTERM here (a Jupyter interrupt reaches this process alone) goes to every
    process once, as if each had got it: the first stops them after the step they agreed on, the
    second at once. The processes lead process groups of their own (`_process`), so a terminal's
    Ctrl-C reaches them only this way (one that reached them before, as they started, is held
    there until they run the stage)."""

    def __init__(self, processes: list) -> None:
        super().__init__()
        self.processes = processes

    def ask(self, number: int, frame: Any) -> None:
        for process in self.processes:
            if process.is_alive():
                os.kill(process.pid, signal.SIGINT)


def _as_in_one_process(text: str) -> BaseException:
    """A process's stop or bad-input error as one process raises it, without the traceback."""
    for raised, kind in ((XvoeError, XvoeError), (Stopped, KeyboardInterrupt)):
        said = f"{raised.__module__}.{raised.__qualname__}"
        if said in text:
            return kind(text.rsplit(said, 1)[1].lstrip(":").strip())
    return RuntimeError(text)


class Stopped(Exception):
    """A training process stopped on request (torch's process wrapper takes a KeyboardInterrupt
    for its parent's doing and exits as if the work were done)."""


def _process(rank: int, world: int, port: int, train: Callable[..., Any], recipe: Recipe | None,
             kwargs: dict, parent: int) -> None:
    end_with_parent(parent)
    os.setpgid(0, 0)        # out of the terminal's group: Ctrl-C comes once, through ForwardedStops
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank),
                      WORLD_SIZE=str(world), LOCAL_WORLD_SIZE=str(world), OMP_NUM_THREADS="1",
                      TORCHELASTIC_USE_AGENT_STORE="True")     # the store is the parent's: join it, do not host it
    torch.set_num_threads(1)
    if recipe is not None:
        RECIPES[recipe.name] = recipe
    try:
        # started with Ctrl-C held (`on_cores`): one that came meanwhile stops the stage here
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        train(**kwargs)
    except KeyboardInterrupt as stop:
        raise Stopped(str(stop)) from None
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
