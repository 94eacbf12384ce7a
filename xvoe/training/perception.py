"""The perception stage: training the Component VAE on a split's frames, and loading it."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from ..errors import XvoeError
from ..models.config import from_dict, override, override_resumed, to_dict
from ..models.perception import ComponentVAE, PerceptionConfig
from .checkpoints import load_checkpoint, load_weights, recorded_input, resolve_run
from .config import TrainConfig
from .data import ShardedFrames
from .distributed import setup_distributed, start_process
from .loop import Job, checkpoint_path, fit
from .recipes import DEFAULT_RECIPE, recipe, recipe_of
from .stages import PERCEPTION

__all__ = ["load_perception", "train_perception"]


def load_perception(model: str | os.PathLike, device: str | torch.device = "cpu"):
    """The trained ComponentVAE of a checkpoint (in eval mode) and the checkpoint's contents."""
    path = resolve_run(model)
    state = load_checkpoint(path, PERCEPTION, device)
    vae = ComponentVAE(from_dict(PerceptionConfig, state["config"][PERCEPTION]))
    load_weights(vae, state, path)
    state["path"] = str(path)
    return vae.to(device).eval(), state


def _perception_configs(recipe_name: str, run_dir: Path, resume: bool, **train_overrides: Any):
    """Model and training configs: the checkpoint's when resuming, else the recipe's, with overrides."""
    ckpt = checkpoint_path(run_dir, PERCEPTION)
    if resume and ckpt.exists():
        state = load_checkpoint(ckpt, PERCEPTION)
        model_config = from_dict(PerceptionConfig, state["config"][PERCEPTION])
        train_config, recipe_name = from_dict(TrainConfig, state["train"]), recipe_of(state["config"])
    else:
        chosen = recipe(recipe_name)
        model_config, train_config = chosen.perception, chosen.perception_train
    return recipe_name, model_config, override(train_config, **train_overrides)


def train_perception(data: str | os.PathLike | None, run_dir: str | os.PathLike, *, recipe_name: str = DEFAULT_RECIPE,
                     resume: bool = False, overwrite: bool = False, progress: bool = True,
                     model_overrides: dict | None = None, device: str = "cpu", **train_overrides: Any) -> Path:
    """What `xvoe train perception` does; also works under torchrun. A resumed run may leave
    out `data`: it trains on the split it started on. `device`: where it trains (cpu, cuda,
    cuda:N, mps)."""
    place = setup_distributed(device)
    run_dir = Path(run_dir)
    if data is None:
        if not (resume and checkpoint_path(run_dir, PERCEPTION).exists()):
            raise XvoeError("--data is required to start a run (the training split file)")
        ckpt = checkpoint_path(run_dir, PERCEPTION)
        data = recorded_input(load_checkpoint(ckpt), ckpt, "data")
    recipe_name, model_config, config = _perception_configs(recipe_name, run_dir, resume, **train_overrides)
    if resume and checkpoint_path(run_dir, PERCEPTION).exists():
        model_config = override_resumed(model_config, model_overrides, what="perception run")
    else:
        model_config = override(model_config, **(model_overrides or {}))
    config = start_process(config, place)
    model = ComponentVAE(model_config)
    frames = ShardedFrames(str(data), image_size=model_config.image_size, latent_dim=model_config.latent_dim,
                           batch_size=config.batch_size, shards=config.data_shards, rank=place.rank,
                           world=place.world, max_videos=config.max_videos, seed=config.seed,
                           airborne_share=config.airborne_share)
    job = Job(PERCEPTION, model, frames.batch, {"recipe": recipe_name, PERCEPTION: to_dict(model_config)},
              items=lambda batch: batch.images, meta={"data": str(Path(data).resolve())})
    return fit(job, config, run_dir, place=place, resume=resume, overwrite=overwrite, progress=progress)
