"""A learned proposal for the hidden object's whole trajectory, frame by frame.

The NLL's SMC draws frame t of a never-seen object from a proposal given the particle's past.
Transformer 2 gives per-frame marginals, which do not move like the dynamics; this small network
gives q(z_t | z_{t-1}, the dynamics' prediction for t, Transformer 2's marginal at t, t), trained
by the CSIS objective on true trajectories (`xvoe.training.trajectory`), so that its draws are
whole trajectories that the dynamics find likely and that go where the marginals point.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from .dynamics import mlp


@dataclass(frozen=True)
class TrajectoryConfig:
    latent_dim: int = 16        # D
    frames: int = 15            # T of the training videos: t is fed as t / frames
    hidden: int = 128           # width of the MLP
    layers: int = 2             # its hidden layers
    # the scale of frames after the first before training (zero weights): about the dynamics'
    # one-step RMS error per latent (docs/decisions.md, "NLL motion sigma")
    step_scale: float = 0.2
    # the network moves the log-scale by at most this either way (a soft limit): a learned
    # component that collapses or explodes would cost the SMC its weights
    scale_range: float = 4.0


class TrajectoryProposal(nn.Module):
    """A diagonal Gaussian for frame t of the hidden slot, vectorised over particles.

    With zero weights in its last layer it is "move like the dynamics": mean the dynamics'
    prediction and scale `step_scale` (t > 0), Transformer 2's marginal mean and scale (t = 0);
    the network learns corrections to that, from differences (where the marginal is relative to
    the prediction, the step the prediction takes) so that it does not have to learn positions."""

    def __init__(self, config: TrajectoryConfig):
        super().__init__()
        self.config = config
        d = config.latent_dim
        self.net = mlp(5 * d + 2, config.hidden, config.layers, 2 * d)
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, t: int | Tensor, previous: Tensor, prediction: Tensor, marginal_loc: Tensor,
                marginal_scale: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and scale (n, D) of frame t's latent. t: an int or (n,) frame indices;
        previous: z_{t-1} (n, D), ignored where t = 0; prediction: the dynamics' mean of frame t
        given the particle's past (n, D), the latent prior's mean at t = 0; marginal_loc and
        marginal_scale: Transformer 2's for frame t (n, D)."""
        dtype, own = prediction.dtype, self.net[0].weight.dtype
        previous, prediction, marginal_loc, marginal_scale = (
            x.to(own) for x in (previous, prediction, marginal_loc, marginal_scale))
        t = torch.as_tensor(t, device=prediction.device).expand(len(prediction))
        first = (t == 0)[:, None]
        previous = torch.where(first, prediction, previous)
        log_marginal = marginal_scale.log()
        features = torch.cat([prediction, marginal_loc - prediction, prediction - previous, log_marginal,
                              previous, first.float(), (t[:, None].float() / self.config.frames)], dim=-1)
        change, log_change = self.net(features).chunk(2, dim=-1)
        base = torch.where(first, marginal_loc, prediction)
        base_log = torch.where(first, log_marginal, torch.full_like(log_marginal, self.config.step_scale).log())
        limit = self.config.scale_range
        scale = torch.exp(base_log + limit * torch.tanh(log_change / limit))
        return (base + change).to(dtype), scale.to(dtype)

    def log_density(self, z: Tensor, t: int | Tensor, previous: Tensor, prediction: Tensor, marginal_loc: Tensor,
                    marginal_scale: Tensor) -> Tensor:
        """log q(z | ...) (n,), summed over the latents."""
        loc, scale = self(t, previous, prediction, marginal_loc, marginal_scale)
        return torch.distributions.Normal(loc, scale).log_prob(z.to(loc.dtype)).sum(-1)
