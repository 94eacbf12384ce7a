"""The trajectory stage: the NLL's learned proposal of whole trajectories, by CSIS.

`xvoe train trajectory` takes a trained XPL (RUN_DIR/xpl.pt, with proposal.pt beside it if the
proposal stage ran), frozen, and trains a `TrajectoryProposal` on the training videos: a seen
object is hidden in every frame, as a never-seen one is at test; Transformer 1 refines the rest
and Transformer 2 proposes the hidden slot's marginals; the object's true latents (its hidden
spans bridged, as the proposal stage's targets) are put back to get the dynamics' teacher-forced
prediction of each frame; the loss is -sum_t log q(z_t | z_{t-1}, prediction_t, marginal_t), the
CSIS objective (simulated pairs, -log q of the truth). Only the new network trains.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from ..errors import XvoeError
from ..models.config import from_dict, override, override_resumed, to_dict
from ..models.reasoning import hide_slot
from ..models.trajectory import TrajectoryConfig, TrajectoryProposal
from ..models.xpl import XPL, permute_slots
from .checkpoints import load_checkpoint
from .loop import Dist, Job, checkpoint_path, fit, seed_everything, set_threads
from .recipes import TrainConfig, recipe, recipe_of
from .xpl import ProposalBatch, ProposalBatches, fingerprint, run_xpl

# the networks whose outputs the trajectory proposal reads: Transformer 2 too (its marginals),
# so a proposal.pt trained again makes an older trajectory.pt refuse to load
TRAJECTORY_INPUTS = ("transformer1.", "transformer2.", "dynamics.")


def xpl_fingerprint(xpl: XPL) -> str:
    """Which XPL (with its proposal.pt, if any) a trajectory.pt belongs to."""
    return fingerprint(xpl.state_dict(), TRAJECTORY_INPUTS)


class TrajectoryBatches(ProposalBatches):
    """The proposal stage's batches (walls that stay, hidden spans bridged), the rebuilt slot
    always a seen object that is not a wall: the trajectory proposal learns how objects move."""

    def hidden_slots(self, rng: np.random.Generator, video: np.ndarray, order: np.ndarray) -> np.ndarray:
        index = torch.from_numpy(video)
        objects = (self.visible[index].any(dim=1) & ~self.walls[index]).numpy()     # (B, K), original order
        weights = rng.random(objects.shape) * objects
        original = np.where(objects.any(axis=1), weights.argmax(axis=1), rng.integers(0, self.slots, len(video)))
        inverse = np.argsort(order, axis=1)
        return inverse[np.arange(len(video)), original]


class TrajectoryNetworks(nn.Module):
    """What the stage trains: the proposal alone. The XPL is held outside the module's
    parameters and state (a tuple is not registered), so trajectory.pt holds the proposal only."""

    def __init__(self, xpl: XPL, proposal: TrajectoryProposal, empty: Tensor):
        super().__init__()
        self.proposal = proposal
        self.frozen = (xpl.eval(),)
        self.register_buffer("empty", empty, persistent=False)

    def forward(self, batch: ProposalBatch) -> dict[str, Tensor]:
        loc, scale, target, prediction, real = self.inputs(batch)
        batch_size, frames, dim = target.shape
        previous = torch.cat([torch.zeros_like(target[:, :1]), target[:, :-1]], dim=1)
        predicted = torch.cat([torch.zeros_like(target[:, :1]), prediction], dim=1)      # the prior's mean at t = 0
        t = torch.arange(frames).repeat(batch_size)

        def flat(x: Tensor) -> Tensor:
            return x.reshape(-1, dim)

        log_q = self.proposal.log_density(flat(target), t, flat(previous), flat(predicted), flat(loc), flat(scale))
        per_video = log_q.reshape(batch_size, frames).sum(dim=1)
        weight = real.to(per_video.dtype)
        loss = -(per_video * weight).sum() / weight.sum().clamp_min(1)
        # the same for the untrained component (the dynamics' step, Transformer 2 at t = 0): the gain so far
        with torch.no_grad():
            base = torch.cat([loc[:, :1], prediction], dim=1)
            spread = torch.cat([scale[:, :1], torch.full_like(prediction, self.proposal.config.step_scale)], dim=1)
            start = torch.distributions.Normal(base, spread).log_prob(target).sum(dim=(1, 2))
            start = -(start * weight).sum() / weight.sum().clamp_min(1)
        return {"loss": loss, "nll": loss.detach(), "untrained_nll": start}

    @torch.no_grad()
    def inputs(self, batch: ProposalBatch) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Transformer 2's marginal mean and scale of the hidden slot (B, T, D), its true
        latents (B, T, D), the dynamics' teacher-forced prediction of frames 1..T-1 (B, T-1, D),
        and which videos hide a real object (B,)."""
        xpl, = self.frozen
        raw, visible, target = permute_slots(batch.mean, batch.visible, batch.target, order=batch.order)
        walls = batch.walls.gather(1, batch.order)
        rows = torch.arange(len(raw))
        hidden = batch.hidden
        real = visible[rows, :, hidden].any(dim=1) & ~walls[rows, hidden]
        rebuilt = ~hide_slot(visible.shape, hidden)
        unseen = visible & ~rebuilt                         # the object was never seen, as at test
        refined = xpl.refine(torch.where(rebuilt.unsqueeze(-1), self.empty, raw), unseen, walls)
        mean, scale = xpl.propose(refined, unseen, hidden)
        loc = mean[rows, :, hidden]
        scale = scale[rows, :, hidden].clamp_min(xpl.config.reasoning.min_scale)
        truth = target[rows, :, hidden]
        scene = refined.clone()
        scene[rows, :, hidden] = truth
        prediction = xpl.predict(scene, walls)[rows, :, hidden]
        return loc, scale, truth, prediction, real


def train_trajectory(run_dir: str | os.PathLike, latents: str | os.PathLike | None = None, *, resume: bool = False,
                     overwrite: bool = False, progress: bool = True, model_overrides: dict | None = None,
                     **train_overrides: Any) -> Path:
    """What `xvoe train trajectory` does: train RUN_DIR/trajectory.pt, the NLL's learned
    proposal of whole trajectories, for the frozen RUN_DIR/xpl.pt (with its proposal.pt)."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise XvoeError("the trajectory stage runs in one process (a few minutes): launch it without torchrun")
    run_dir = Path(run_dir)
    xpl_path, xpl, xpl_state = run_xpl(run_dir, "the xpl stage (and the proposal stage)")
    if not xpl.config.use_reasoning:
        raise XvoeError(f"{xpl_path} has no Transformer 2 (a PLATO model?): the trajectory proposal needs one")
    ckpt = checkpoint_path(run_dir, "trajectory")
    recipe_name = recipe_of(xpl_state["config"])
    if resume and ckpt.exists():
        state = load_checkpoint(ckpt)
        config = from_dict(TrainConfig, state["train"])
        model_config = override_resumed(from_dict(TrajectoryConfig, state["config"]["trajectory"]), model_overrides,
                                        what="trajectory run")
        latents = latents or state["meta"]["latents"]      # the run's own cache, not the xpl stage's
    else:
        latents = latents or xpl_state["meta"].get("latents")
        config = recipe(recipe_name).trajectory_train
        reasoning = xpl.config.reasoning
        model_config = override(TrajectoryConfig(latent_dim=reasoning.latent_dim, frames=reasoning.frames),
                                **(model_overrides or {}))
    if latents is None or not Path(latents).is_file():
        raise XvoeError(f"no latent cache at {latents}: give --data, the training split's latent cache")
    config = override(override(config, **train_overrides), data_shards=1)
    set_threads(config, 1)
    seed_everything(config.seed)
    batches = TrajectoryBatches(str(latents), batch_size=config.batch_size, shards=1, max_videos=config.max_videos,
                                seed=config.seed)
    if batches.mean.shape[-1] != model_config.latent_dim:
        raise XvoeError(f"{latents} holds {batches.mean.shape[-1]} latents per slot, {xpl_path} "
                        f"{model_config.latent_dim}: encode the split with that run's perception module")
    meta = {"latents": str(Path(latents).resolve()), "xpl": str(xpl_path.resolve()),
            "xpl_fingerprint": xpl_fingerprint(xpl), "proposal": xpl_state.get("proposal")}
    place = Dist(device=torch.device("cpu"))
    networks = TrajectoryNetworks(xpl, TrajectoryProposal(model_config), batches.empty)
    job = Job("trajectory", networks, batches.batch, {"recipe": recipe_name, "trajectory": to_dict(model_config)},
              meta=meta)
    return fit(job, config, run_dir, place=place, resume=resume, overwrite=overwrite, progress=progress)


def load_trajectory(path: str | os.PathLike, xpl: XPL) -> TrajectoryProposal:
    """trajectory.pt for this XPL (as loaded with its proposal.pt), in eval mode; an error if it
    was trained for another one."""
    state = load_checkpoint(path)
    if state.get("stage") != "trajectory":
        raise XvoeError(f"{path} is a {state.get('stage')} checkpoint, not a trajectory one")
    if state["meta"].get("xpl_fingerprint") != xpl_fingerprint(xpl):
        raise XvoeError(f"{path} was trained for another xpl.pt or proposal.pt than the ones beside it; retrain "
                        "it (xvoe train trajectory --overwrite) or move it away")
    proposal = TrajectoryProposal(from_dict(TrajectoryConfig, state["config"]["trajectory"]))
    proposal.load_state_dict({name.removeprefix("proposal."): value for name, value in state["model"].items()})
    return proposal.eval()


def with_trajectory(xpl: XPL, state: dict) -> dict:
    """Attach the NLL's learned proposal, trajectory.pt beside the xpl.pt that `load_xpl` read
    (`state`), as `xpl.trajectory`, where the trajectory stage ran and the proposal.pt it was
    trained on was loaded; the checkpoint's contents, with "trajectory" its path if attached."""
    learned = Path(state["path"]).parent / "trajectory.pt"
    proposal_loaded = "proposal" in state or not (learned.parent / "proposal.pt").is_file()
    if state["stage"] == "xpl" and proposal_loaded and learned.is_file():
        xpl.trajectory = load_trajectory(learned, xpl)
        state["trajectory"] = str(learned)
    return state
