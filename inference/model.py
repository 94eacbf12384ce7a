"""The analysis-by-synthesis model of a video with possibly one fully hidden object.

Generative story: the latents of the objects that are seen are given (they live inside the
`Scene`); a hidden object exists with prior probability p (site `exists`); if it does, its
latent trajectory starts from the latent prior and follows the scene's dynamics with
Gaussian transitions (sites `z_0` ... `z_{T-1}`); every frame is rendered from all latents
and observed under a Gaussian pixel likelihood (site `frames`), less a penalty for every pixel
the hidden object shows in front of everything else (the encoder reported no object there) and
for every pixel it draws short of an object's area (a latent that draws nothing is no object).

The guide proposes `exists` from its own amortised probability and the trajectory from a
per-frame Gaussian (in XPL: Transformer 2's mean and scale), by default fused with the
model's own step: each z_t is drawn from the product of the dynamics' Gaussian given the
particle's past and the per-frame Gaussian, as if the latter were a measurement of z_t (the
locally optimal proposal of a Kalman filter), its scale widened (`proposal_widening`): it says
where the object is on the whole, not anew each frame, and a proposal narrower than the
posterior misses part of the evidence, where a wider one only costs variance. Drawn
independently frame by frame, a trajectory jitters by the per-frame scale, far more than the
dynamics' transition noise, and every particle holding an object pays hundreds of nats for it.
The trajectory sites are masked by `exists` in both model and guide, so a particle without a
hidden object is weighted by p(no object) p(x | no object) / q(no object) alone: an exact
trans-dimensional importance sampler. Every site lives in a `particles` plate, for
`inference.importance`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import pyro
import pyro.distributions as dist
import torch
from pyro import poutine
from torch import Tensor, nn

from xvoe.models.nll import InferenceConfig


class Drawing(NamedTuple):
    """What a scene draws with a hidden object on trajectories (M, T, D)."""

    frames: Tensor      # (M, T, ...) the expected frames
    exposure: Tensor    # (M, T) pixels the hidden object shows in front of everything else
    area: Tensor        # (M, T) pixels it draws in front of the background, before any wall hides it


class Scene(Protocol):
    """What the model needs from a scene (the learned XPL one, or a linear one in tests)."""

    frames: int

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        """Mean and scale (N, D) of the hidden object's first latent."""

    def transition(self, history: Tensor) -> Tensor:
        """Mean (N, D) of the next latent given the hidden object's latents so far (N, t, D)."""

    def empty(self) -> Tensor:
        """Expected frames (T, ...) without a hidden object."""

    def draw(self, trajectory: Tensor) -> Drawing:
        """Expected frames (M, T, ...) with a hidden object on each trajectory (M, T, D), the
        pixels where it would be in plain view (its exposure) and the pixels it draws at all."""


def drawing_cost(config: InferenceConfig, drawing: Drawing) -> Tensor:
    """Nats (M, T) float64 the hidden object's drawing costs besides its pixels' likelihood: each
    pixel it shows in plain view, where the encoder saw nothing, and each pixel it falls short
    of an object's area (a share of the drawn frames' H x W): the object must be there, hidden
    behind a wall, not a shadow of one."""
    frame_pixels = drawing.frames.shape[-2] * drawing.frames.shape[-1]
    shortfall = (config.object_area * frame_pixels - drawing.area.to(torch.float64)).clamp_min(0.0)
    return config.exposure_penalty * drawing.exposure.to(torch.float64) + config.presence_penalty * shortfall


def pixel_log_normaliser(pixels: int, sigma: float) -> float:
    """log of the normaliser of an isotropic Gaussian over `pixels` values: the pixel
    likelihood's constant, also that of a reference drawing scored the same way."""
    return pixels * (math.log(sigma) + 0.5 * math.log(2 * math.pi))


@dataclass
class Proposal:
    """The guide's parameters for one video."""

    p_exists: Tensor                # scalar
    loc: Tensor                     # (T, D)
    scale: Tensor                   # (T, D)


class HiddenObjectModel(nn.Module):
    def __init__(self, scene: Scene, config: InferenceConfig):
        super().__init__()
        self.scene, self.config = scene, config
        self._steps: dict[int, tuple[Tensor, Tensor, Tensor]] = {}   # the guide's dynamics steps, for the model

    def model(self, frames: Tensor, proposal: Proposal | None = None, particles: int = 1) -> Tensor:
        if isinstance(self.scene, nn.Module):
            pyro.module("scene", self.scene)
        with pyro.plate("particles", particles, dim=-1):
            exists = pyro.sample("exists", dist.Bernoulli(torch.tensor(self.config.prior_hidden, device=frames.device)))
            with poutine.mask(mask=exists.bool()):
                loc, scale = self.scene.initial(particles)
                trajectory = [pyro.sample("z_0", dist.Normal(loc, scale).to_event(1))]
                for t in range(1, self.scene.frames):
                    loc = self._transition(torch.stack(trajectory, dim=1), exists.bool())
                    step = dist.Normal(loc, self.config.transition_sigma).to_event(1)
                    trajectory.append(pyro.sample(f"z_{t}", step))
            pyro.factor("frames", self.pixel_log_likelihood(torch.stack(trajectory, dim=1), exists.bool(), frames))
            if hasattr(self.scene, "seen_motion"):
                predicted, seen, observed = self.scene.seen_motion(torch.stack(trajectory, dim=1), exists)
                motion = dist.Normal(predicted, self.config.motion_sigma).mask(observed[..., None]).to_event(3)
                pyro.sample("seen_motion", motion, obs=seen.expand(particles, *seen.shape))
        return exists

    def pixel_log_likelihood(self, trajectory: Tensor, alive: Tensor, frames: Tensor) -> Tensor:
        """log N(frames | rendered frames, pixel_sigma^2) of each particle (N,), less the cost
        of its hidden object's drawing (`drawing_cost`), summed in float64. Every particle
        without a hidden object shows the same frames, so they are rendered and scored once; a
        (N, T, 4, H, W) density of 64 particles cost a third of the scoring time."""
        sigma = self.config.pixel_sigma
        constant = pixel_log_normaliser(frames.numel(), sigma)

        def log_density(expected: Tensor) -> Tensor:
            squares = ((expected - frames) / sigma).square().flatten(start_dim=expected.dim() - frames.dim())
            return -0.5 * squares.sum(dim=-1, dtype=torch.float64) - constant

        result = torch.empty(len(alive), dtype=torch.float64, device=frames.device)
        if not alive.all():
            result[~alive] = log_density(self.scene.empty())
        if alive.any():
            drawing = self.scene.draw(trajectory[alive])
            result[alive] = log_density(drawing.frames) - drawing_cost(self.config, drawing).sum(-1)
        return result

    def _transition(self, history: Tensor, alive: Tensor) -> Tensor:
        """The dynamics' mean for the particles that hold an object (alive (N,) bool). The
        others' trajectory sites are masked out, so their mean is never used: the dynamics,
        the dearest step, skip them (they keep their last latent, a finite stand-in). The
        model, replayed on the guide's draws, asks for the steps the guide computed: they are
        kept and handed back when the history is the same."""
        steps = history.shape[1]
        kept = self._steps.get(steps)
        if kept is not None and torch.equal(kept[0], history) and torch.equal(kept[1], alive):
            return kept[2]
        loc = history[:, -1].clone()
        if alive.any():
            loc[alive] = self.scene.transition(history[alive])
        self._steps[steps] = (history, alive, loc)
        return loc

    def guide(self, frames: Tensor, proposal: Proposal, particles: int = 1) -> Tensor:
        with pyro.plate("particles", particles, dim=-1):
            exists = pyro.sample("exists", dist.Bernoulli(proposal.p_exists))
            alive = exists.bool()
            trajectory: list[Tensor] = []
            with poutine.mask(mask=alive):
                for t in range(self.scene.frames):
                    loc, scale = proposal.loc[t], proposal.scale[t]
                    if self.config.guide_follows_dynamics:
                        if t == 0:
                            step, spread = self.scene.initial(particles)
                        else:
                            step = self._transition(torch.stack(trajectory, dim=1), alive)
                            spread = torch.full_like(step, self.config.transition_sigma)
                        loc, scale = fuse(step, spread, loc, scale * self.config.proposal_widening)
                    trajectory.append(pyro.sample(f"z_{t}", dist.Normal(loc, scale).to_event(1)))
        return exists


def fuse(loc_a: Tensor, scale_a: Tensor, loc_b: Tensor, scale_b: Tensor) -> tuple[Tensor, Tensor]:
    """The normalised product of two diagonal Gaussians: precisions add, means weigh by them."""
    precision_a, precision_b = scale_a ** -2, scale_b ** -2
    precision = precision_a + precision_b
    return (loc_a * precision_a + loc_b * precision_b) / precision, precision ** -0.5


class LinearGaussianScene(nn.Module):
    """A scene whose hidden object moves linearly and is seen through a linear camera:
    z_0 ~ N(m0, s0), z_t = A z_{t-1} + N(0, q), frame_t = background + exists * H z_t.
    Its evidence has a closed form (a Kalman filter), so it checks the estimator end to end."""

    def __init__(self, frames: int, initial_mean: Tensor, initial_scale: float, transition: Tensor,
                 camera: Tensor, background: Tensor):
        super().__init__()
        self.frames = frames
        self.register_buffer("initial_mean", initial_mean)
        self.initial_scale = initial_scale
        self.register_buffer("A", transition)
        self.register_buffer("H", camera)
        self.register_buffer("background", background)

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        mean = self.initial_mean.expand(particles, -1)
        return mean, torch.full_like(mean, self.initial_scale)

    def transition(self, history: Tensor) -> Tensor:
        return history[:, -1] @ self.A.T

    def empty(self) -> Tensor:
        return self.background.expand(self.frames, -1)

    def render(self, trajectory: Tensor) -> Tensor:
        return self.background + trajectory @ self.H.T              # (M, T, obs)

    def draw(self, trajectory: Tensor) -> Drawing:
        """The frames, no exposure and no shortfall: this scene's object is seen through a
        linear camera, nothing hides it and it need not draw itself."""
        steps = trajectory.shape[:2]
        return Drawing(self.render(trajectory), trajectory.new_zeros(steps), trajectory.new_full(steps, math.inf))
