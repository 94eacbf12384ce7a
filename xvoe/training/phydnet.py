"""The PhyDNet baseline's training stage: next-frame prediction on the training split's pixels.

`xvoe train phydnet --data train.h5 --out RUN_DIR` writes RUN_DIR/phydnet.pt and
phydnet.csv through the shared loop. A batch is a set of whole videos; which ones is drawn
from a generator seeded by (seed, step, shard), so a resumed or multi-process run sees the
same batches as one uninterrupted process.
"""
from __future__ import annotations

import math
import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import XvoeError
from ..models.config import from_dict, override, override_resumed, to_dict
from ..models.phydnet import PhyDNet, PhyDNetConfig, PhyDNetObjective, widen_lstm_kernel
from ..scenes import store
from .checkpoints import load_checkpoint, load_weights, recorded_input, resolve_run, save_checkpoint
from .config import TrainConfig
from .data import check_size, focus_on, owned_shards
from .distributed import Dist, setup_distributed, start_process
from .loop import Job, checkpoint_path, fit
from .recipes import DEFAULT_RECIPE, recipe, recipe_of
from .stages import PHYDNET

__all__ = ["train_phydnet", "load_phydnet"]

_LOSS_FIELDS = ("change_weight", "moment_weight")   # PhyDNetConfig fields a resumed run may change


class _VideoBatches:
    """The shards of a split file that one process owns, in memory as uint8 RGBD, and its batches.

    With `focus_group`, a `focus_share` of each shard's part of a batch is drawn from that
    group's videos with a wall (the ones where a hidden object must be remembered), the rest
    uniformly from all of the shard's videos.
    """

    def __init__(self, path: str, *, image_size: int, batch_size: int, shards: int, rank: int = 0, world: int = 1,
                 max_videos: int = 0, seed: int = 0, focus_group: str = "", focus_share: float = 0.0):
        with store.open_dataset(path, split="train") as file:
            check_size(file, image_size, "PhyDNet")
            count, *video = file["rgbd"].shape        # a video as the model reads it: (T, H, W, 4) floats
            owned = owned_shards(path, count, batch_size=batch_size, item_bytes=4 * math.prod(video), shards=shards,
                                 rank=rank, world=world, max_videos=max_videos)
            self.rgbd = torch.from_numpy(store.read_frames(file, "rgbd", owned.start, owned.stop))
        self.focus = focus_on(path, owned, focus_group, focus_share)
        self.shards, self.bounds, self.per_shard = owned.shards, owned.bounds, owned.per_shard
        self.start, self.seed = owned.start, seed

    def batch(self, step: int) -> Tensor:
        """uint8 videos (B, T, H, W, 4): the local part of the global batch of `step`."""
        picks = [self.focus.draw(np.random.default_rng([self.seed, step, shard]), i, start, stop, self.per_shard)
                 for i, (shard, (start, stop)) in enumerate(zip(self.shards, self.bounds))]
        return self.rgbd[torch.from_numpy(np.concatenate(picks) - self.start)]


def _phydnet_configs(recipe_name: str, run_dir: Path, resume: bool, data: str | os.PathLike | None
                    ) -> tuple[str, PhyDNetConfig, TrainConfig, str]:
    """Model and training configs and the data file: the checkpoint's when resuming, else the recipe's."""
    ckpt = checkpoint_path(run_dir, PHYDNET)
    if resume and ckpt.exists():
        state = load_checkpoint(ckpt, PHYDNET)
        model_config = from_dict(PhyDNetConfig, state["config"][PHYDNET])
        train_config, recipe_name = from_dict(TrainConfig, state["train"]), recipe_of(state["config"])
        return recipe_name, model_config, train_config, str(data or recorded_input(state, ckpt, "data"))
    if data is None:
        raise XvoeError(f"nothing to resume in {run_dir}: give the training split to start a run")
    chosen = recipe(recipe_name)
    return recipe_name, chosen.phydnet, chosen.phydnet_train, str(data)


def train_phydnet(data: str | os.PathLike | None, run_dir: str | os.PathLike, *, recipe_name: str = DEFAULT_RECIPE,
                  resume: bool = False, overwrite: bool = False, progress: bool = True,
                  model_overrides: dict | None = None, device: str = "cpu", **train_overrides: Any) -> Path:
    """What `xvoe train phydnet` does (also under torchrun) on `device`; returns RUN_DIR/phydnet.pt."""
    place = setup_distributed(device)
    run_dir = Path(run_dir)
    recipe_name, model_config, config, data = _phydnet_configs(recipe_name, run_dir, resume, data)
    ckpt = checkpoint_path(run_dir, PHYDNET)
    resuming = resume and ckpt.exists()
    if resuming:
        model_config = override_resumed(model_config, model_overrides, _LOSS_FIELDS, "PhyDNet")
    else:
        model_config = override(model_config, **(model_overrides or {}))
    config = override(config, **train_overrides)
    if config.lstm_kernel not in (0, model_config.lstm_kernel):
        if not resuming:
            raise XvoeError("lstm_kernel widens the gates of a trained PhyDNet in a later phase; a fresh run "
                            "takes its kernel from the model config (--set model.lstm_kernel=K)")
        _widen_checkpoint(ckpt, config.lstm_kernel, place)
        model_config = replace(model_config, lstm_kernel=config.lstm_kernel)   # a loss field's override kept
    config = start_process(config, place)
    batches = _VideoBatches(data, image_size=model_config.image_size, batch_size=config.batch_size,
                           shards=config.data_shards, rank=place.rank, world=place.world,
                           max_videos=config.max_videos, seed=config.seed, focus_group=config.focus_group,
                           focus_share=config.focus_share)
    job = Job(PHYDNET, PhyDNetObjective(PhyDNet(model_config)), batches.batch,
              {"recipe": recipe_name, PHYDNET: to_dict(model_config)}, meta={"data": str(Path(data).resolve())})
    return fit(job, config, run_dir, place=place, resume=resume, overwrite=overwrite, progress=progress)


def _widen_checkpoint(path: Path, kernel: int, place: Dist) -> None:
    """Rewrite a PhyDNet run's checkpoint with its ConvLSTM gates widened to `kernel`
    (`widen_lstm_kernel`: the same predictions to begin with) and Adam afresh, its step, RNG
    states and loss log kept, so that the resumed phase trains the wider gates."""
    if place.main:
        state = load_checkpoint(path, PHYDNET)
        narrow = from_dict(PhyDNetConfig, state["config"][PHYDNET])
        widened = {}
        for key in ("model", "trained"):        # "trained" beside "model" when the run averages its weights
            if key in state:
                objective = PhyDNetObjective(PhyDNet(narrow))
                load_weights(objective, state, path, key)
                wider = PhyDNetObjective(widen_lstm_kernel(objective.net, kernel))
                widened[key] = wider.state_dict()
        if "optimizer" in state:     # an un-stepped Adam over the same parameters, in the same order
            widened["optimizer"] = torch.optim.Adam(wider.parameters()).state_dict()
        config = {**state["config"], PHYDNET: to_dict(wider.net.config)}
        save_checkpoint(path, {**state, **widened, "config": config})
    if place.world > 1:
        torch.distributed.barrier()


def load_phydnet(model: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[PhyDNet, dict]:
    """A trained PhyDNet (in eval mode) from a checkpoint or run directory, and the checkpoint's contents."""
    path = resolve_run(model, PHYDNET)
    state = load_checkpoint(path, PHYDNET, device)
    objective = PhyDNetObjective(PhyDNet(from_dict(PhyDNetConfig, state["config"][PHYDNET])))
    load_weights(objective, state, path)
    state["path"] = str(path)
    return objective.net.to(device).eval(), state
