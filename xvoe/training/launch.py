"""A training stage in one process per core, from Python: what `torchrun --standalone` does.

On a small CPU, one-thread processes that share a batch through DistributedDataParallel
train faster than one process with as many threads: the models' layers are too small to
keep a second thread busy (docs/decisions.md, "Training stages on every core").
"""
from __future__ import annotations

import os
import socket
from collections.abc import Callable
from typing import Any

import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from ..errors import XvoeError
from .recipes import RECIPES, Recipe


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


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
    try:
        mp.start_processes(_process, args=(processes, free_port(), train, recipe, kwargs), nprocs=processes,
                           join=True, start_method="spawn")
    except mp.ProcessRaisedException as error:
        # bad input found in a process reads as it would in one process, without the traceback
        said = f"{XvoeError.__module__}.{XvoeError.__qualname__}: "
        text = str(error)
        if said in text:
            raise XvoeError(text.rsplit(said, 1)[1].strip()) from None
        raise


def _process(rank: int, world: int, port: int, train: Callable[..., Any], recipe: Recipe | None,
             kwargs: dict) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), LOCAL_RANK=str(rank),
                      WORLD_SIZE=str(world), LOCAL_WORLD_SIZE=str(world), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    if recipe is not None:
        RECIPES[recipe.name] = recipe
    try:
        train(**kwargs)
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
