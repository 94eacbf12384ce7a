"""The analysis-by-synthesis model of a video with possibly one fully hidden object, written
once, frame by frame, in Pyro.

Generative story: the latents of the objects that are seen are given (they live inside the
`Scene`), up to which explanation of them holds: where a seen object goes out of sight and is
seen again, it is one object, or with prior probability p2 two identical ones (site `two`;
`inference.identity`); a hidden object exists with prior probability p (site `exists`); if it does, its
latent starts from the latent prior (site `z_0`) and follows the scene's dynamics with
Gaussian transitions (sites `z_1` ... `z_{T-1}`). Frame t is rendered from all latents and
observed under a Gaussian pixel likelihood (site `x_t`), less a penalty for every pixel the
hidden object shows in front of everything else (the encoder reported no object there) and
for every pixel it draws short of an object's area (a latent that draws nothing is no
object); the dynamics then predict frame t + 1, and the seen objects' latents there are
observed under that prediction (site `motion_{t+1}`): a hidden object that explains a ball
bouncing back raises the likelihood. An object seen for the first time is observed under the
latent prior instead: the dynamics would predict it from Transformer 1's fills alone, and those
were filled in from that very sighting.

The model is written as Pyro's `SMCFilter` models are, an `init` and a `step` per frame, with
every site in a `particles` plate that the caller opens; `model` runs them over the whole
video. Each particle carries its explanation of the seen objects as the scene's `version`. The
guide (`guide_init`, `guide_step`, `guide`) proposes `exists` from its own amortised
probability, `two` from its prior, and each z_t from Transformer 2's per-frame Gaussian fused
with the dynamics' step: the product of the two Gaussians, as if the former were a measurement of z_t
(the locally optimal proposal of a Kalman filter), its scale widened, since it says where the
object is on the whole, not anew each frame, and a proposal narrower than the posterior misses
part of the evidence. The
trajectory sites are masked by `exists` in both model and guide, so a
particle without a hidden object is weighted by p(no object) p(x | no object) / q(no object)
alone: an exact trans-dimensional importance sampler. Sequential Monte Carlo and importance
sampling (`inference.model_steps`) both run these methods through Pyro's trace and replay; no density
is written anywhere else.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import pyro
import pyro.distributions as dist
import torch
from pyro import poutine
from torch import Tensor, nn

from xvoe.models.nll import InferenceConfig

__all__ = ["InferenceConfig", "State", "Drawing", "Step", "Scene", "drawing_cost", "pixel_log_normaliser",
           "Proposal", "HiddenObjectModel"]

State = dict[str, Any]     # what a particle carries from frame to frame: exists, trajectory, the dynamics' memory


class Drawing(NamedTuple):
    """What a scene draws of a hidden object in one frame, for M particles."""

    frames: Tensor      # (M, ...) the expected frame
    exposure: Tensor    # (M,) pixels the hidden object shows in front of everything else
    area: Tensor        # (M,) pixels it draws in front of the background, before any wall hides it


class Step(NamedTuple):
    """The dynamics after frame t, for every particle."""

    loc: Tensor                 # (N, D) mean of the hidden object's next latent
    memory: Any                 # the scene's state to carry on (the dynamics' memory), None if it has none
    seen: Tensor | None         # (N, M, D) the predicted next latents of the seen moving objects, None if none


class Scene(Protocol):
    """What the model needs from a scene (the learned XPL one, or a linear one in tests)."""

    frames: int
    versions: int       # explanations of the seen objects: 1, or 2 where one may be two identical ones

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        """Mean and scale (N, D) of an object's latent with no history: the hidden object's first,
        and a seen object's at its first sighting."""

    def empty_frame(self, t: int) -> Tensor:
        """The expected frame t of every version (V, ...) without a hidden object."""

    def draw_frame(self, t: int, latents: Tensor, version: Tensor) -> Drawing:
        """Frame t of the versions `version` (M,) with a hidden object at each of the latents (M, D)."""

    def advance(self, t: int, latents: Tensor, alive: Tensor, version: Tensor, memory: Any) -> Step:
        """The dynamics run on frame t of each particle's version, the hidden slot holding
        `latents` (N, D) where `alive`."""

    def seen_motion(self, t: int) -> tuple[Tensor, Tensor, Tensor] | None:
        """The seen moving objects' latents (V, M, D) at frame t, which the encoder saw (V, M) and
        which it saw for the first time (V, M)."""

    def select(self, memory: Any, index: Tensor) -> Any:
        """The memory of the particles `index` (resampling)."""


def drawing_cost(config: InferenceConfig, drawing: Drawing) -> Tensor:
    """Nats float64 the hidden object's drawing costs besides its pixels' likelihood: each pixel
    it shows in plain view, where the encoder saw nothing, and each pixel it falls short of an
    object's area (a share of the drawn frame's H x W): the object must be there, hidden behind
    a wall, not a shadow of one."""
    frame_pixels = drawing.frames.shape[-2] * drawing.frames.shape[-1]
    shortfall = (config.object_area * frame_pixels - drawing.area.to(torch.float64)).clamp_min(0.0)
    return config.exposure_penalty * drawing.exposure.to(torch.float64) + config.presence_penalty * shortfall


def pixel_log_normaliser(pixels: int, sigma: float) -> float:
    """log of the normaliser of an isotropic Gaussian over `pixels` values: the pixel
    likelihood's constant, also that of a reference drawing scored the same way."""
    return pixels * (math.log(sigma) + 0.5 * math.log(2 * math.pi))


def _pixel_log_density(expected: Tensor, observed: Tensor, sigma: float) -> Tensor:
    """log N(observed | expected, sigma^2) of each leading entry of expected (n, ...) against one
    observed frame, summed in float64: a frame's thousands of pixel terms would lose in float32
    the digits that tell two videos apart."""
    squares = ((expected - observed) / sigma).square().flatten(start_dim=1)
    return -0.5 * squares.sum(dim=1, dtype=torch.float64) - pixel_log_normaliser(observed.numel(), sigma)


@dataclass
class Proposal:
    """The guide's parameters for one video."""

    p_exists: Tensor                # scalar, what the guide draws `exists` from
    loc: Tensor                     # (T, D)
    scale: Tensor                   # (T, D)
    # scalar: XPL's existence head's own probability, before the guide keeps it off 0 and 1; what
    # decides which runs are made (`inference.evidence.hidden_runs`)
    head: Tensor


class HiddenObjectModel(nn.Module):
    def __init__(self, scene: Scene, config: InferenceConfig):
        super().__init__()
        self.scene, self.config = scene, config
        self.frames = scene.frames

    @property
    def device(self) -> torch.device:
        """Where the scene's tensors are; the model's own follow them."""
        return self.scene.empty_frame(0).device

    # --- the model ------------------------------------------------------------------------------

    def init(self, state: State, particles: int) -> None:
        exists = pyro.sample("exists", dist.Bernoulli(logits=self.prior_logit()))
        state.update(exists=exists.bool(), version=self.identity(particles), trajectory=None, memory=None)
        state["loc"], state["scale"] = self.scene.initial(particles)

    def identity(self, particles: int) -> Tensor:
        """Each particle's explanation of the seen objects (N,) long: 1 where one seen object is
        two identical ones (site `two`, only where the scene has that version)."""
        if self.scene.versions == 1:
            return torch.zeros(particles, dtype=torch.long, device=self.device)
        return pyro.sample("two", dist.Bernoulli(logits=self.prior_logit(self.config.prior_two))).long()

    def prior_logit(self, p: float | None = None) -> Tensor:
        """log p - log(1 - p) of a hidden object (or of `p`), in float64: a probability held in
        float32 is clamped to its epsilon, and a prior under 1e-7 would lose its nats."""
        p = self.config.prior_hidden if p is None else p
        return torch.tensor(math.log(p) - math.log1p(-p), dtype=torch.float64, device=self.device)

    def step(self, state: State, t: int, frame: Tensor) -> None:
        alive, z = state["exists"], state["loc"]
        if alive.any():     # a trajectory site only where a particle holds an object; no argument checks
            with poutine.mask(mask=alive):
                z = pyro.sample(f"z_{t}", dist.Normal(state["loc"], state["scale"], validate_args=False).to_event(1))
        version = state["version"]
        pyro.factor(f"x_{t}", self.frame_log_likelihood(t, z, alive, version, frame))
        _keep(state, z)
        if t + 1 < self.frames:
            predicted = self.advance(state, t, z)
            sighted = self.scene.seen_motion(t + 1)
            if predicted is not None and sighted is not None:
                latents, seen, first = sighted
                seen, first = seen[version, :, None], first[version, :, None]
                # a first sighting is scored under `initial`'s prior: the dynamics would predict it from fills alone
                prior_loc, prior_scale = (part.double() for part in self.scene.initial(1))
                expected = dist.Normal(torch.where(first, prior_loc, predicted.double()),
                                       torch.where(first, prior_scale, self.config.motion_sigma), validate_args=False)
                pyro.sample(f"motion_{t + 1}", expected.mask(seen).to_event(2), obs=latents[version].double())

    def model(self, frames: Tensor, proposal: Proposal | None = None, particles: int = 1) -> Tensor:
        """The whole video: `init`, then `step` for every frame."""
        state: State = {}
        with pyro.plate("particles", particles, dim=-1):
            self.init(state, particles)
            for t in range(self.frames):
                self.step(state, t, frames[t])
        return state["exists"]

    def site_terms(self, frames: Tensor, given: dict[str, Tensor], particles: int) -> list[tuple[str, Tensor]]:
        """Each sample site's name and log-density (particles,) of `model` traced over `frames`
        with the sites in `given` fixed: the trace behind the exact branches."""
        trace = poutine.trace(poutine.condition(self.model, data=given)).get_trace(frames, None, particles)
        trace.compute_log_prob()
        return [(name, node["log_prob"]) for name, node in trace.nodes.items()
                if node["type"] == "sample" and name != "particles"]

    def frame_log_likelihood(self, t: int, latents: Tensor, alive: Tensor, version: Tensor, frame: Tensor) -> Tensor:
        """log N(frame t | rendered frame, pixel_sigma^2) of each particle (N,), less the cost of
        its hidden object's drawing (`drawing_cost`), in float64. The particles without a hidden
        object show their version's one frame: each version's is scored once."""
        sigma = self.config.pixel_sigma
        result = torch.empty(len(alive), dtype=torch.float64, device=frame.device)
        if not alive.all():
            result[~alive] = _pixel_log_density(self.scene.empty_frame(t), frame, sigma)[version[~alive]]
        if alive.any():
            drawing = self.scene.draw_frame(t, latents[alive], version[alive])
            result[alive] = _pixel_log_density(drawing.frames, frame, sigma) - drawing_cost(self.config, drawing)
        return result

    def advance(self, state: State, t: int, latents: Tensor) -> Tensor | None:
        """Step the scene's dynamics past frame t: the next latent's prior and the seen objects'
        predicted motion (None where the scene has none). No site: the guide runs it too, where it
        goes without the model (`guide`)."""
        step = self.scene.advance(t, latents, state["exists"], state["version"], state["memory"])
        state["loc"], state["memory"] = step.loc, step.memory
        state["scale"] = torch.full_like(step.loc, self.config.transition_sigma)
        return step.seen

    # --- the guide ------------------------------------------------------------------------------

    def guide_init(self, state: State, particles: int, proposal: Proposal | None) -> None:
        existence = dist.Bernoulli(logits=self.prior_logit()) if proposal is None else dist.Bernoulli(proposal.p_exists)
        state["exists"] = pyro.sample("exists", existence).bool()
        state["version"] = self.identity(particles)
        if "loc" not in state:
            state["loc"], state["scale"] = self.scene.initial(particles)

    def guide_step(self, state: State, t: int, proposal: Proposal | None, widenings: tuple[float, ...]) -> Tensor:
        if not state["exists"].any():
            return state["loc"]
        with poutine.mask(mask=state["exists"]):
            return pyro.sample(f"z_{t}", self.proposal_at(t, state, proposal, widenings))

    def guide(self, frames: Tensor, proposal: Proposal | None = None, particles: int = 1,
              widenings: tuple[float, ...] | None = None) -> Tensor:
        """The whole video's proposal (for checks and for importance sampling by whole traces);
        the dynamics are stepped on the guide's own draws."""
        state: State = {}
        widenings = widenings or (self.config.proposal_widening,)
        with pyro.plate("particles", particles, dim=-1):
            self.guide_init(state, particles, proposal)
            state.update(trajectory=None, memory=None)
            for t in range(self.frames):
                z = self.guide_step(state, t, proposal, widenings)
                _keep(state, z)
                if t + 1 < self.frames:
                    self.advance(state, t, z)
        return state["exists"]

    def proposal_at(self, t: int, state: State, proposal: Proposal | None,
                    widenings: tuple[float, ...]) -> dist.TorchDistribution:
        """z_t's proposal: the dynamics' step fused with Transformer 2's marginal widened by each
        of `widenings`, an equal-weight mixture (each component is a function of the particle's
        past, so the mixture's density is the one each draw came from); the dynamics' step alone
        without a proposal (the bootstrap filter)."""
        loc, scale = state["loc"], state["scale"]
        if proposal is None:
            return dist.Normal(loc, scale, validate_args=False).to_event(1)
        mean, spread = proposal.loc[t].expand_as(loc), proposal.scale[t].expand_as(loc)
        fused = [_fuse(loc, scale, mean, spread * widening) for widening in widenings]
        if len(fused) == 1:
            return dist.Normal(*fused[0], validate_args=False).to_event(1)
        locs, scales = torch.stack([f[0] for f in fused], dim=-2), torch.stack([f[1] for f in fused], dim=-2)
        choice = dist.Categorical(logits=torch.zeros(locs.shape[:-1], dtype=locs.dtype, device=locs.device),
                                  validate_args=False)
        return dist.MixtureSameFamily(choice, dist.Normal(locs, scales, validate_args=False).to_event(1),
                                      validate_args=False)


def _keep(state: State, latents: Tensor) -> None:
    """Add a frame's latents (N, D) to the particles' trajectory (N, t, D)."""
    trajectory = state["trajectory"]
    state["trajectory"] = latents[:, None] if trajectory is None else torch.cat([trajectory, latents[:, None]], 1)


def _fuse(loc_a: Tensor, scale_a: Tensor, loc_b: Tensor, scale_b: Tensor) -> tuple[Tensor, Tensor]:
    """The normalised product of two diagonal Gaussians: precisions add, means weigh by them."""
    precision_a, precision_b = scale_a ** -2, scale_b ** -2
    precision = precision_a + precision_b
    return (loc_a * precision_a + loc_b * precision_b) / precision, precision ** -0.5


class _LinearGaussianScene(nn.Module):
    """A scene whose hidden object moves linearly and is seen through a linear camera:
    z_0 ~ N(m0, s0), z_t = A z_{t-1} + N(0, q), frame_t = background_v + exists * H z_t, with
    one background per version (V, P). Its evidence has a closed form (a Kalman filter per
    version), so it checks the estimators end to end."""

    def __init__(self, frames: int, initial_mean: Tensor, initial_scale: float, transition: Tensor,
                 camera: Tensor, background: Tensor):
        super().__init__()
        self.frames = frames
        self.register_buffer("initial_mean", initial_mean)
        self.initial_scale = initial_scale
        self.register_buffer("A", transition)
        self.register_buffer("H", camera)
        self.register_buffer("background", background if background.dim() == 2 else background[None])
        self.versions = len(self.background)

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        mean = self.initial_mean.expand(particles, -1)
        return mean, torch.full_like(mean, self.initial_scale)

    def empty_frame(self, t: int) -> Tensor:
        return self.background

    def draw_frame(self, t: int, latents: Tensor, version: Tensor) -> Drawing:
        """The frame, no exposure and no shortfall: this scene's object is seen through a linear
        camera, nothing hides it and it need not draw itself."""
        count = len(latents)
        return Drawing(self.background[version] + latents @ self.H.T, latents.new_zeros(count),
                       latents.new_full((count,), math.inf))

    def advance(self, t: int, latents: Tensor, alive: Tensor, version: Tensor, memory: None) -> Step:
        return Step(latents @ self.A.T, None, None)

    def seen_motion(self, t: int) -> None:
        return None

    def select(self, memory: None, index: Tensor) -> None:
        return None
