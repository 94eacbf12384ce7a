"""XPL on object latents: two reasoning Transformers and the dynamics, and their losses.

Training reads the latent cache (posterior means and per-frame visibility), never pixels:
Transformer 1 and the dynamics are trained jointly on the dynamics loss over frames 1..T-1
with visible entries fixed to the cached means; Transformer 2 learns, MAE-style, to rebuild a
slot hidden in every frame from Transformer 1's refined latents. PLATO is the same model
without reasoning and without the residual.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from ..domains import NON_NEGATIVE, within
from .dynamics import DynamicsConfig, InteractionLSTM, mlp
from .reasoning import (
    ReasoningConfig,
    ReasoningTransformer,
    gaussian_nll,
    hide_slot,
    never_seen,
    occlusion_keep,
)

__all__ = ["XPLConfig", "XPL", "permute_slots"]


@dataclass(frozen=True)
class XPLConfig:
    reasoning: ReasoningConfig = field(default_factory=ReasoningConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    use_reasoning: bool = True      # False: PLATO (dynamics on the raw means)
    stop_target_gradient: bool = True   # the dynamics target is a constant for Transformer 1
    # the dynamics' input is a constant for Transformer 1 too: it learns its fills from rebuilding
    # seen spans alone (refill), not by making the dynamics' task easier; through the input, the
    # fills of an impossible video drift towards what the dynamics expect and explain it away
    stop_input_gradient: bool = False
    mae_weight: float = within(1.0, NON_NEGATIVE)
    refill_weight: float = within(1.0, NON_NEGATIVE)      # Transformer 1 rebuilding hidden spans of seen frames
    # Transformer 1 also rebuilds the entries of seen objects that lie wholly outside the picture
    # (the simulator says where), as the blank latent the cache holds there. Nothing else trains
    # those fills, yet about a third of the hidden entries of the training videos are such (cubes
    # that fall in from above, balls that roll in), and the MSE score draws them where no wall stands
    outside_refill: bool = False
    permute_slots: bool = True      # slot order carries no meaning: shuffle it in training
    # walls exert no effect in the dynamics, and their own prediction is no part of its loss: a
    # wall stands in a nearer depth lane and touches nothing. Otherwise the dynamics learn the
    # training walls' schedule (lowered over frames 1-3) and carry it into the balls' motion in
    # test videos whose wall stands from the start (S2, S3)
    inert_walls: bool = False
    # Transformer 1 reads no wall entry (and rebuilds none): a wall touches nothing (see
    # inert_walls), so no fill needs it, and a fill that attends to it can take on the wall's
    # latent, which draws a wall where a hidden cube stands (docs/decisions.md, "The XPL
    # stage: walls and fills")
    refill_ignores_walls: bool = False
    # Transformer 2 and the existence head train in the joint stage too; off, in the proposal
    # stage alone, and the joint step costs a third less, since nothing else in it reads them
    # (docs/decisions.md, "Training choices")
    joint_proposal: bool = True


class XPL(nn.Module):
    def __init__(self, config: XPLConfig):
        super().__init__()
        self.config = config
        self.dynamics = InteractionLSTM(config.dynamics)
        if config.use_reasoning:
            self.transformer1 = ReasoningTransformer(config.reasoning)
            self.transformer2 = ReasoningTransformer(config.reasoning)
            # q(a hidden object exists | what Transformer 2 proposes for the slot it filled):
            # the amortised existence probability of the inference model's guide
            self.existence = mlp(2 * config.reasoning.latent_dim * config.reasoning.frames, 64, 1, 1)

    def forward(self, batch) -> dict[str, Tensor]:
        """The training objective of a LatentBatch (what the training loop calls)."""
        return self.losses(batch.mean, batch.visible, batch.order, batch.hidden, batch.refill, batch.walls,
                           batch.outside)

    def predict(self, refined: Tensor, walls: Tensor | None = None) -> Tensor:
        """The dynamics' prediction (B, T-1, K, D) of frames 1..T-1 from refined latents (B, T, K, D),
        each from the frames before it; walls (B, K) bool are inert if the config says so."""
        return self.dynamics(refined[:, :-1], walls if self.config.inert_walls else None)

    def refine(self, z: Tensor, visible: Tensor, walls: Tensor | None = None) -> Tensor:
        """Fill the frames in which a seen object is occluded (Transformer 1); walls (B, K)
        bool, the wall slots, are needed if Transformer 1 ignores them."""
        if not self.config.use_reasoning:
            return z
        return self.fill(z, occlusion_keep(visible), self.unread_walls(visible, walls))

    def fill(self, z: Tensor, keep: Tensor, unread: Tensor | None) -> Tensor:
        """Transformer 1's latents (B, T, K, D): z where kept, filled elsewhere."""
        return self.transformer1(z, keep, unread)[0]

    def unread_walls(self, visible: Tensor, walls: Tensor | None) -> Tensor | None:
        """Transformer 1's unread entries (B, T, K): the walls' if the config says so, else None."""
        if not self.config.refill_ignores_walls:
            return None
        if walls is None:
            raise ValueError("this XPL's Transformer 1 ignores the walls: refine needs the wall slots (B, K)")
        return walls[:, None, :].expand_as(visible)

    def explain(self, refined: Tensor, visible: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Transformer 2's proposal for an object seen in no frame.

        The first never-seen slot of each video is hidden in all frames (slot order has no
        meaning, so any such slot will do). Returns the completed latents, the predicted
        scales and the slot used, -1 where every slot was seen (latents then unchanged).
        """
        unseen = never_seen(visible)
        slot = torch.where(unseen.any(1), unseen.float().argmax(1), torch.full_like(unseen[:, 0], -1, dtype=torch.long))
        mean, scale = self.propose(refined, visible, slot)
        return mean, scale, slot

    def propose(self, refined: Tensor, visible: Tensor, slot: Tensor) -> tuple[Tensor, Tensor]:
        """Transformer 2's latents and scales (B, T, K, D) with slot `slot` (B,) hidden in every
        frame and rebuilt (-1: none; latents unchanged, scales 0 outside the rebuilt slot)."""
        proposed = ~hide_slot(visible.shape, slot.clamp_min(0))
        proposed[slot < 0] = False
        mean, scale = self.transformer2(refined, ~proposed)
        return torch.where(proposed.unsqueeze(-1), mean, refined), scale * proposed.unsqueeze(-1)

    def existence_logit(self, mean: Tensor, scale: Tensor) -> Tensor:
        """Logit (B,) that the filled slot holds a real object, from Transformer 2's mean and
        scale for it over the frames (B, T, D); videos shorter than the model are zero-padded."""
        features = torch.cat([mean, torch.log(scale)], dim=-1)
        missing = self.config.reasoning.frames - features.shape[1]
        features = nn.functional.pad(features, (0, 0, 0, missing))
        return self.existence(features.flatten(1)).squeeze(-1)

    def losses(self, z: Tensor, visible: Tensor, order: Tensor | None = None,
               hidden: Tensor | None = None, refill: Tensor | None = None,
               walls: Tensor | None = None, outside: Tensor | None = None) -> dict[str, Tensor]:
        """z: (B, T, K, D) cached means; visible: (B, T, K) bool. `order` (B, K), a slot
        order per video, `hidden` (B,), the slot Transformer 2 must rebuild, and `refill`
        (B, T, K) bool, seen entries Transformer 1 must rebuild, are drawn here unless given
        (the training data give them, so that batches are reproducible). `walls` (B, K) bool:
        the wall slots (used with inert_walls; none if not given). `outside` (B, T, K) bool: hidden
        entries outside the picture, which Transformer 1 must fill with the cached (blank) latent.

        Transformer 1 learns from two signals: the dynamics loss, and rebuilding seen entries
        hidden from it (spans like the ones a wall hides). The second keeps its fills on the
        latents the decoder knows; with the dynamics loss alone, fills drift to latents that
        decode to nothing or to blots. With stop_input_gradient it learns from the second alone."""
        if refill is None:
            refill = torch.zeros_like(visible)
        if walls is None:
            walls = torch.zeros_like(visible[:, 0])
        if outside is None:
            outside = torch.zeros_like(visible)
        if self.config.permute_slots and self.training:
            z, visible, refill, walls, outside = permute_slots(
                z, visible, refill, walls.unsqueeze(1).expand_as(visible), outside, order=order)
            walls = walls[:, 0]
        refill = refill & visible
        out = {}
        if self.config.use_reasoning:
            keep, unread = occlusion_keep(visible), self.unread_walls(visible, walls)
            refined = self.fill(z, keep & ~refill, unread)
            rebuilt = refill | (outside & ~keep)
            if unread is not None:                 # what Transformer 1 does not read, it does not rebuild
                rebuilt = rebuilt & ~unread
            if rebuilt.any():
                out["refill"] = (_squared_norm(refined - z) * rebuilt).sum() / rebuilt.sum()
            fills = refined if not self.config.stop_target_gradient else refined.detach()
            target = torch.where(visible.unsqueeze(-1), z, fills)[:, 1:]
        else:
            refined, target = z, z[:, 1:]
        inputs = refined.detach() if self.config.stop_input_gradient else refined
        error = _squared_norm(self.predict(inputs, walls) - target)
        if self.config.inert_walls:
            moving = (~walls)[:, None, :].expand_as(error)
            out["dynamics"] = (error * moving).sum() / moving.sum().clamp_min(1)
        else:
            out["dynamics"] = error.mean()
        if self.config.use_reasoning and self.config.joint_proposal:
            refined = torch.where(refill.unsqueeze(-1), z, refined)    # what Transformer 2 sees at test
            slot = hidden if hidden is not None else torch.randint(z.shape[2], (z.shape[0],), device=z.device)
            out.update(self.proposal_losses(refined.detach(), visible, slot))
        zero = torch.zeros((), device=z.device)
        out["loss"] = (out["dynamics"] + self.config.refill_weight * out.get("refill", zero)
                       + self.config.mae_weight * out.get("mae", zero) + out.get("existence", zero))
        return out

    def proposal_losses(self, refined: Tensor, visible: Tensor, slot: Tensor, beta: float = 0.0) -> dict[str, Tensor]:
        """Transformer 2 and the existence head, on refined latents (B, T, K, D) with slot
        `slot` (B,) hidden in every frame: the Gaussian NLL of what was hidden, -log q(z | rest)
        (the beta-NLL if beta > 0, see reasoning.gaussian_nll), and the cross-entropy of whether
        the slot held a seen object."""
        keep = hide_slot(visible.shape, slot)
        mean, scale = self.transformer2(refined, keep)
        scale = scale.clamp_min(self.config.reasoning.min_scale)
        out = {"mae": gaussian_nll(mean, scale, refined, ~keep, beta)}
        rows = torch.arange(len(slot), device=refined.device)
        logit = self.existence_logit(mean[rows, :, slot].detach(), scale[rows, :, slot].detach())
        exists = visible[rows, :, slot].any(dim=1).to(logit.dtype)
        out["existence"] = nn.functional.binary_cross_entropy_with_logits(logit, exists)
        out["mae_mse"] = (((mean - refined) ** 2).sum(-1) * (~keep)).sum() / (~keep).sum()
        return out


def _squared_norm(error: Tensor) -> Tensor:
    """Squared error summed over the latent axis."""
    return (error ** 2).sum(-1)


def permute_slots(*tensors: Tensor, order: Tensor | None = None) -> tuple[Tensor, ...]:
    """Apply one slot order per video (B, K), random unless given, to tensors (B, T, K, ...)."""
    batch, _, slots = tensors[0].shape[:3]
    if order is None:
        order = torch.argsort(torch.rand(batch, slots, device=tensors[0].device), dim=1)
    return tuple(torch.gather(t, 2, order[:, None, :].reshape(batch, 1, slots, *[1] * (t.dim() - 3))
                              .expand(-1, t.shape[1], -1, *t.shape[3:])) for t in tensors)
