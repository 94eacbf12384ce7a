"""The proposal stage: Transformer 2 and the existence head of a trained XPL, trained further
on objects hidden in every frame of the training videos, through the shared loop."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from ..models.config import from_dict, override, override_resumed, to_dict
from ..models.reasoning import hide_slot
from ..models.xpl import XPL, XPLConfig, permute_slots
from .checkpoints import load_checkpoint, recorded_input
from .config import TrainConfig
from .distributed import setup_distributed, start_process
from .latent_batches import ProposalBatch, ProposalBatches
from .loop import Job, checkpoint_path, fit
from .recipes import recipe, recipe_of
from .stages import PROPOSAL
from .stages import XPL as XPL_STAGE  # beside the network XPL
from .xpl import fingerprint, run_xpl

__all__ = ["ProposalNetworks", "train_proposal"]

_PROPOSAL_BETA = 0.5   # the proposal stage's loss is the beta-NLL: with the plain NLL a hard latent's scale
                       # grows and its mean stops learning (docs/decisions.md, "Training choices")


class ProposalNetworks(nn.Module):
    """What the proposal stage trains: Transformer 2 and the existence head of a trained XPL,
    registered under the XPL's own names (so the stage's checkpoint overlays xpl.pt), while
    Transformer 1 and the dynamics stay frozen outside it.

    Transformer 2 sees the other slots as Transformer 1 refines them with the rebuilt slot
    emptied, as at test, where the hidden object was never seen: refined with the object in
    view, a partly occluded ball's fill carries where the object stands, a clue that is gone
    at test."""

    def __init__(self, xpl: XPL, empty: Tensor):
        super().__init__()
        self.transformer2, self.existence = xpl.transformer2, xpl.existence
        self.refine, self.losses = xpl.refine, xpl.proposal_losses
        self.register_buffer("empty", empty, persistent=False)

    def forward(self, batch: ProposalBatch) -> dict[str, Tensor]:
        walls = batch.walls.unsqueeze(1).expand_as(batch.visible)
        raw, visible, target, walls = permute_slots(batch.mean, batch.visible, batch.target, walls, order=batch.order)
        rebuilt = ~hide_slot(visible.shape, batch.hidden)
        with torch.no_grad():
            context = self.refine(torch.where(rebuilt.unsqueeze(-1), self.empty, raw), visible & ~rebuilt, walls[:, 0])
        out = self.losses(torch.where(rebuilt.unsqueeze(-1), target, context), visible, batch.hidden, _PROPOSAL_BETA)
        out["loss"] = out["mae"] + out["existence"]
        return out


def train_proposal(run_dir: str | os.PathLike, latents: str | os.PathLike | None = None, *, resume: bool = False,
                   overwrite: bool = False, progress: bool = True, model_overrides: dict | None = None,
                   device: str = "cpu", **train_overrides: Any) -> Path:
    """What `xvoe train proposal` does: train Transformer 2 and the existence head of
    RUN_DIR/xpl.pt further on -log q(hidden object | the rest), on objects hidden in every
    frame of the training videos (the simulator's trajectories, encoded), into
    RUN_DIR/proposal.pt. In the joint stage they get one step in each of the XPL's few steps
    and a hidden object is a rare draw; the explanation and the NLL's proposal need more.
    The network is the xpl.pt's: `model_overrides` that change it are refused.
    Also under torchrun (or `launch.on_cores`), as the XPL stage, on `device`."""
    run_dir = Path(run_dir)
    place = setup_distributed(device)
    xpl_path, xpl, xpl_state = run_xpl(run_dir, "the xpl stage", proposal=False)
    ckpt = checkpoint_path(run_dir, PROPOSAL)
    recipe_name = recipe_of(xpl_state["config"])
    if resume and ckpt.exists():
        state = load_checkpoint(ckpt, PROPOSAL)
        config = from_dict(TrainConfig, state["train"])
        xpl.config = from_dict(XPLConfig, state["config"][XPL_STAGE])
    else:
        config = recipe(recipe_name).proposal_train
    xpl.config = override_resumed(xpl.config, model_overrides, what="proposal run")
    config = start_process(override(config, **train_overrides), place)
    latents = latents or recorded_input(xpl_state, xpl_path, "latents")
    batches = ProposalBatches(str(latents), batch_size=config.batch_size, shards=config.data_shards, rank=place.rank,
                              world=place.world, max_videos=config.max_videos, seed=config.seed,
                              focus_group=config.focus_group, focus_share=config.focus_share)
    meta = {"latents": str(Path(latents).resolve()), XPL_STAGE: str(xpl_path.resolve()),
            "xpl_fingerprint": fingerprint(xpl_state["model"])}
    networks = ProposalNetworks(xpl.to(place.device), batches.empty)
    job = Job(PROPOSAL, networks, batches.batch, {"recipe": recipe_name, XPL_STAGE: to_dict(xpl.config)}, meta=meta)
    return fit(job, config, run_dir, place=place, resume=resume, overwrite=overwrite, progress=progress)
