"""The XPL and PLATO training stages, on the latent cache, through the shared loop.

`xvoe train xpl` trains Transformer 1 and the dynamics jointly on the dynamics loss
and Transformer 2 on Transformer 1's refined latents; `xvoe train plato` trains the dynamics
alone (no residual) on the raw means; `xvoe train xpl-noresidual` gives the paper's ablation
(Fig. 5a). Their batches are drawn by `latent_batches`; the proposal stage, which trains on
top of xpl.pt, is `proposal`; a trained XPL is loaded with its proposal by `load_xpl`.
"""
from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ..errors import XvoeError
from ..models.config import from_dict, override, override_resumed, to_dict
from ..models.devices import resolve_device
from ..models.nll import InferenceConfig
from ..models.xpl import XPL, XPLConfig
from ..scenes import store
from .checkpoints import load_checkpoint, load_weights, recorded_input, resolve_run
from .config import TrainConfig
from .distributed import setup_distributed, start_process
from .latent_batches import LatentBatches
from .latents import check_cache, encode_split, encoder_key, open_latents, split_cache
from .loop import Job, checkpoint_path, fit
from .perception import load_perception
from .recipes import DEFAULT_RECIPE, RECIPES, recipe, recipe_of
from .stages import PROPOSAL, STAGES
from .stages import XPL as XPL_STAGE  # beside the network XPL

__all__ = ["TRAINED_ON_LATENTS", "encoded_cache", "fingerprint", "latent_cache_for", "load_xpl", "model_nll",
           "nll_origin", "nll_settings_of", "run_xpl", "stage_config", "train_xpl"]

# the stages this module trains from the latent cache alone (the proposal stage builds on xpl.pt)
TRAINED_ON_LATENTS = tuple(name for name, entry in STAGES.items() if entry.variant and entry.reads == "latents")


def stage_config(base: XPLConfig, name: str, shape: tuple) -> XPLConfig:
    """The XPL config `base` fitted to the cache's (T, K, D) and to the stage's variant: what the
    data and the stage decide, whatever the recipe or an override says."""
    frames, slots, dim = shape
    entry = STAGES[name]
    reasoning = replace(base.reasoning, latent_dim=dim, slots=slots, frames=max(frames, base.reasoning.frames))
    dynamics = replace(base.dynamics, latent_dim=dim, residual=entry.residual)
    return replace(base, reasoning=reasoning, dynamics=dynamics, use_reasoning=entry.variant == XPL_STAGE)


def train_xpl(latents: str | os.PathLike | None, run_dir: str | os.PathLike, *, stage: str = XPL_STAGE,
              recipe_name: str = DEFAULT_RECIPE, resume: bool = False, overwrite: bool = False, progress: bool = True,
              model_overrides: dict | None = None, device: str = "cpu", **train_overrides: Any) -> Path:
    """What `xvoe train xpl|plato|xpl-noresidual` does (also under torchrun, on `device`), into RUN_DIR/STAGE.pt.
    `model_overrides` change XPLConfig fields of a fresh run (dotted names reach nested
    configs; `stop_target_gradient=False` lets the dynamics loss reach Transformer 1 through the
    target too); a resumed run keeps its network."""
    if stage not in TRAINED_ON_LATENTS:
        raise XvoeError(f"stage must be one of {', '.join(TRAINED_ON_LATENTS)}, not {stage!r}")
    place = setup_distributed(device)
    ckpt = checkpoint_path(run_dir, stage)
    state = load_checkpoint(ckpt, stage) if resume and ckpt.exists() else None
    if state is None and latents is None:
        raise XvoeError(f"nothing to resume in {run_dir}: give the latent cache to start a run")
    latents = latents or recorded_input(state, ckpt, "latents")
    recipe_name, model_config, config = _xpl_configs(state, stage, recipe_name, model_overrides)
    config = start_process(override(config, **train_overrides), place)
    batches = LatentBatches(str(latents), batch_size=config.batch_size, shards=config.data_shards, rank=place.rank,
                            world=place.world, max_videos=config.max_videos, seed=config.seed,
                            walls=model_config.inert_walls or model_config.refill_ignores_walls,
                            outside=model_config.outside_refill,
                            focus_group=config.focus_group, focus_share=config.focus_share)
    if state is None:       # a resumed network is its checkpoint's, fitted when it started
        model_config = stage_config(model_config, stage, batches.shape)
    stored = {"recipe": recipe_name, XPL_STAGE: to_dict(model_config)}
    if STAGES[stage].nll:      # the model the NLL surprise runs on keeps its recipe's settings of it
        stored["nll"] = to_dict(model_nll(state["config"]) if state else recipe(recipe_name).nll)
    job = Job(stage, _network(model_config), batches.batch, stored, meta={"latents": str(Path(latents).resolve())})
    return fit(job, config, run_dir, place=place, resume=resume, overwrite=overwrite, progress=progress)


def _xpl_configs(state: dict | None, stage: str, recipe_name: str,
                 model_overrides: dict | None) -> tuple[str, XPLConfig, TrainConfig]:
    """The recipe's name, the model config with `model_overrides` and the training config: the
    checkpoint's `state` when resuming (its network kept), else the recipe's."""
    if state is not None:
        model_config = override_resumed(from_dict(XPLConfig, state["config"][XPL_STAGE]), model_overrides,
                                        what=f"{stage} run")
        return recipe_of(state["config"]), model_config, from_dict(TrainConfig, state["train"])
    chosen = recipe(recipe_name)
    return recipe_name, override(chosen.xpl, **(model_overrides or {})), chosen.training(stage)


def _network(config: XPLConfig) -> XPL:
    """A fresh XPL to train; Transformer 2 and the existence head frozen where the proposal stage
    trains them, so that DistributedDataParallel expects no gradient of them."""
    model = XPL(config)
    if config.use_reasoning and not config.joint_proposal:
        for part in (model.transformer2, model.existence):
            part.requires_grad_(False)
    return model


def nll_settings_of(config: dict) -> InferenceConfig | None:
    """The NLL settings an xpl checkpoint's `config` stores; None where it stores none (made
    before they were stored)."""
    return from_dict(InferenceConfig, config["nll"]) if "nll" in config else None


def model_nll(config: dict) -> InferenceConfig:
    """The NLL settings of the model an xpl checkpoint's `config` holds: those it stores; where it
    stores none, its recipe's; where this xvoe has not its recipe, InferenceConfig's defaults
    (`nll_origin` says which)."""
    origin = nll_origin(config)
    if origin == "checkpoint":
        return nll_settings_of(config)
    return recipe(recipe_of(config)).nll if origin == "recipe" else InferenceConfig()


def nll_origin(config: dict) -> str:
    """Where `model_nll` takes an xpl checkpoint's NLL settings from: "checkpoint", "recipe" or "defaults"."""
    if nll_settings_of(config) is not None:
        return "checkpoint"
    return "recipe" if recipe_of(config) in RECIPES else "defaults"


def latent_cache_for(data: str | os.PathLike, run_dir: str | os.PathLike, perception: str | None = None,
                     progress: bool = True, device: str = "cpu") -> Path:
    """The latent cache to train on: `data` itself if it is one; for a split file, the cache
    RUN_DIR/latents-NAME.h5, encoded first (on `device`) with the run's perception module if missing."""
    data = Path(data)
    try:
        open_latents(data).close()
        return data
    except XvoeError:
        pass
    cache = _default_cache(data, run_dir)
    if cache.exists():
        check_cache(cache, data)
    else:
        with store.open_dataset(data, split="train"):
            pass
        encode_split(perception or run_dir, data, cache, progress=progress, device=device)
    return cache


def _default_cache(data: str | os.PathLike, run_dir: str | os.PathLike) -> Path:
    """Where a run keeps the latent cache of the split `data`: RUN_DIR/latents-NAME.h5."""
    return Path(run_dir) / f"latents-{Path(data).stem}.h5"


def encoded_cache(data: str | os.PathLike, run_dir: str | os.PathLike, perception: str | None = None,
                  device: str = "cpu") -> Path:
    """Where `xvoe encode` writes the latent cache of the split `data` by default: a training
    split's in the run (`_default_cache`); a test split's beside it (`split_cache` of the
    perception module, `perception` or the run's, encoding on `device`), where every score of
    that perception reads it."""
    with store.open_hdf5(data) as file:
        kind = file.attrs.get("split")
    if kind != "test":
        return _default_cache(data, run_dir)
    return split_cache(data, encoder_key(load_perception(perception or run_dir)[0], resolve_device(device)))


def fingerprint(state: dict[str, Tensor], prefixes: tuple[str, ...] = ("transformer1.", "dynamics.")) -> str:
    """A short hash of the frozen networks' weights: which xpl.pt a proposal checkpoint belongs to."""
    digest = hashlib.sha256()
    for name in sorted(state):
        if name.startswith(prefixes):
            digest.update(name.encode())
            digest.update(state[name].detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def run_xpl(run_dir: Path, needs: str, **loading: bool) -> tuple[Path, XPL, dict]:
    """RUN_DIR/xpl.pt, loaded (`load_xpl` with `loading`), for a stage that trains on top of it;
    an error naming what to train first (`needs`) if it is missing."""
    xpl_path = checkpoint_path(run_dir, XPL_STAGE)
    if not xpl_path.is_file():
        raise XvoeError(f"no xpl.pt in {run_dir}: train {needs} first")
    return (xpl_path, *load_xpl(xpl_path, **loading))


def load_xpl(model: str | os.PathLike, stage: str = XPL_STAGE, device: str | torch.device = "cpu",
             proposal: bool = True) -> tuple[XPL, dict]:
    """A trained XPL (or PLATO) model in eval mode, and its checkpoint's contents. An xpl.pt
    with a proposal.pt beside it (the proposal stage ran) gets that checkpoint's Transformer 2
    and existence head, unless `proposal` is False."""
    path = resolve_run(model, stage)
    state = load_checkpoint(path, stage, device)
    xpl = XPL(from_dict(XPLConfig, state["config"][XPL_STAGE]))
    load_weights(xpl, state, path)
    tuned = path.parent / STAGES[PROPOSAL].checkpoint
    if proposal and state["stage"] == XPL_STAGE and tuned.is_file():
        extra = load_checkpoint(tuned, PROPOSAL, device)
        if extra["meta"].get("xpl_fingerprint") != fingerprint(state["model"]):
            raise XvoeError(f"{tuned} was trained on another xpl.pt than {path}; retrain it "
                            "(xvoe train proposal --overwrite) or move it away")
        load_weights(xpl, extra, tuned, strict=False)
        xpl.config = from_dict(XPLConfig, extra["config"][XPL_STAGE])     # how its Transformer 2 is used, too
        state[PROPOSAL] = str(tuned)
    elif proposal and state["stage"] == XPL_STAGE and not xpl.config.joint_proposal:
        raise XvoeError(f"{path} leaves Transformer 2 to the proposal stage, and no proposal.pt is beside it: "
                        f"train it first (xvoe train proposal --out {path.parent})")
    state["path"] = str(path)
    return xpl.to(device).eval(), state
