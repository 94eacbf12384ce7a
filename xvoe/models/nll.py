"""The settings of the NLL surprise, as data.

They live with the networks' configs, below training, so that a recipe can hold them and a
checkpoint can store them; `inference/` runs the Pyro model they parameterise.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..domains import COUNT, NON_NEGATIVE, POSITIVE, SHARE, Domain, within

__all__ = ["InferenceConfig"]


@dataclass(frozen=True)
class InferenceConfig:
    """The NLL surprise's settings: a recipe's, stored in the xpl checkpoint it trains."""

    # p: prior probability that a hidden object exists
    prior_hidden: float = within(0.5, Domain(0, 1, open_low=True, open_high=True))
    # p2: prior probability that a seen object that goes out of sight and is seen again is two
    # identical ones (0: never; inference.identity). Chosen on the validation split
    # (docs/decisions.md, "Two identical objects")
    prior_two: float = within(0.1, Domain(0, 1, open_high=True))
    # standard deviation of the pixel likelihood: wider than the reconstruction's RMS error, whose
    # errors come in blobs, so that the pixel terms do not drown the seen objects' motion
    # (docs/decisions.md, "The NLL's settings")
    pixel_sigma: float = within(0.5, POSITIVE)
    transition_sigma: float = within(0.1, POSITIVE)   # standard deviation of the hidden object's dynamics
    # nats per pixel of the hidden object's exposure (what it shows in front of everything else):
    # the encoder reported no object in its slot, and that silence is evidence against one in the
    # open; without it a never-seen object is drawn in plain view to patch what the seen slots
    # reconstruct badly (docs/decisions.md, "The NLL's settings")
    exposure_penalty: float = within(12.0, NON_NEGATIVE)
    # nats per pixel the hidden object draws short of `object_area` (a share of the frame's pixels)
    # in front of the background, before any wall hides it: a latent that draws nothing is no
    # object, yet the dynamics let it push the seen ones, and it explained impossible events in
    # plain view at the price of no exposure (docs/decisions.md, "The NLL's settings")
    presence_penalty: float = within(12.0, NON_NEGATIVE)
    object_area: float = within(0.008, SHARE)
    # standard deviation of the seen objects' latents around the dynamics: a scale chosen on the
    # validation split, not the dynamics' measured error (docs/decisions.md, "The NLL's settings")
    motion_sigma: float = within(0.2, POSITIVE)
    particles: int = within(64, COUNT)
    # gradient steps on the proposal's mean before the full run (guide.out_of_sight; a pilot goes without)
    refine_steps: int = within(5, NON_NEGATIVE)
    refine_rate: float = within(0.1, NON_NEGATIVE)        # their Adam learning rate
    # nats a frame of the proposal's mean may cost before it is moved
    refine_tolerance: float = within(1.0, NON_NEGATIVE)
    # Transformer 2's scales are multiplied by this before the fusion: they are each frame's
    # marginal uncertainty, not fresh evidence about that frame, and too narrow for what a video
    # leaves open (docs/decisions.md, "The NLL's settings")
    proposal_widening: float = within(3.0, POSITIVE)
    # "smc": sequential Monte Carlo over frames with existence summed out (inference.smc);
    # "importance": the same model and guide never resampled, the guide proposing existence too
    method: str = "smc"
    # SMC resamples when the ESS falls below this share of the particles
    resample_threshold: float = within(0.5, SHARE)
    # SMC first runs this many particles (0: none), or several pilots in turn (a tuple, smallest
    # first); where the branch with a hidden object then trails the one without by more than
    # smc_pilot_margin nats, it changes log p(x) by less than exp(-margin) and the larger runs
    # are skipped (most videos show every object)
    smc_pilot: int | tuple[int, ...] = within(1, NON_NEGATIVE)
    smc_pilot_margin: float = within(30.0, NON_NEGATIVE)
    # no pilot where XPL's existence head's probability is above this (1.0: pilots everywhere):
    # a small pilot can miss a hidden object that XPL's existence head is sure of, and the
    # video's NLL then swings by hundreds of nats between seeds (docs/decisions.md, "The
    # NLL's settings")
    smc_pilot_skip_exists: float = within(0.5, SHARE)
    # no run with a hidden object at all where the head's probability is under this (0: a pilot
    # everywhere): on the validation splits every such video's pilot trailed by 94 nats or more,
    # and its NLL is the same to the bit without it (docs/decisions.md, "The NLL's settings")
    smc_object_floor: float = within(0.05, SHARE)
    # proposal_widening for the SMC (None: the same); several: an equal-weight mixture of the
    # proposals with each. The SMC reweights every frame, so a pull towards Transformer 2's
    # marginals costs weight variance at each step: the wide component keeps the particles near
    # the dynamics, the narrow one finds the hypotheses that the marginals point at
    smc_proposal_widening: float | tuple[float, ...] | None = within((3.0, 10.0), POSITIVE)
    # full runs pooled where the existence head is surest of an object (above sure_runs_exists:
    # the never-seen-cube videos), each of `particles` around the mean moved out of sight: the
    # evidence is their mean. A never-seen cube is narrow and one run misses it now and then;
    # the mean then loses log K nats where a run alone lost tens or hundreds (docs/decisions.md,
    # "The NLL's settings")
    sure_runs: int = within(2, COUNT)
    # where the head's probability lies between smc_pilot_skip_exists and this, the first full run
    # ends an explanation that trails by more than smc_pilot_margin nats, as a pilot does: there
    # the head is mostly wrong (videos whose every object is seen, where the run finds none), and
    # a never-seen cube is rare (docs/decisions.md, "The NLL's settings")
    sure_runs_exists: float = within(0.95, SHARE)
