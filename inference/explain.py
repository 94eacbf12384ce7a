"""What the Pyro model believes is behind the wall: the hidden object its posterior weights
(the sequential Monte Carlo's final particles over frames, or importance samples where the
model's NLL settings say "importance"), with the posterior probability that it exists and the
effective sample size of the weights, and, where a seen object went out of sight and came
back, the two identical objects that may explain it, with their probability."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from xvoe.errors import XvoeError
from xvoe.evaluation.explain import (
    DRAW_THRESHOLD,
    Explanation,
    look_alike,
    masked,
    read_video_to_explain,
    scene_pictures,
)
from xvoe.evaluation.scorer import EncodedChunk, Scorer
from xvoe.models.perception import to_uint8

from .identity import two_objects
from .model import InferenceConfig
from .surprise import check_particles, explain_surprise, hidden_posterior

__all__ = ["NLLExplanation", "explain_nll", "nll_explanation", "two_object_pictures"]


@dataclass
class NLLExplanation(Explanation):
    p_hidden: float = 0.0       # posterior probability that a hidden object exists
    p_two: float = 0.0          # posterior probability that a seen object is two identical ones
    ess: float = 0.0            # effective sample size of the final weights
    nll: float = 0.0            # the video's surprise, -log p(video), nats
    particles: int = 0          # particles drawn (a pilot's where it sufficed, two runs' where pooled, 0: none)
    holding: int = 0            # of them, those that held a hidden object
    holding_ess: float = 0.0    # the effective sample size among those
    # the heaviest distinct hypotheses of what is hidden, each decoded alone: (label, frames)
    hypotheses: list[tuple[str, np.ndarray]] = field(default_factory=list)
    # the scene behind the wall without the hidden object (None: behind_wall has none)
    behind_empty: np.ndarray | None = None
    # the scene behind the wall as two identical objects, with and without the hidden object,
    # and the frame from which the twin is drawn (None, -1: no seen object may be two)
    two_objects: np.ndarray | None = None
    two_objects_empty: np.ndarray | None = None
    twin_from: int = -1

    @property
    def believed(self) -> bool:
        """Whether the posterior holds a hidden object worth drawing (p above DRAW_THRESHOLD)."""
        return self.p_hidden > DRAW_THRESHOLD and self.holding > 0

    @property
    def p_drawn(self) -> float:
        return self.p_hidden if self.believed and self.draws_hidden else 0.0

    def _story(self, with_hidden: np.ndarray, without: np.ndarray | None) -> np.ndarray:
        """A scene behind the wall with the hidden object at opacity p_hidden (none below the threshold)."""
        if without is None:
            return with_hidden
        if not self.believed:
            return without
        mixed = self.p_hidden * with_hidden.astype(np.float32) + (1 - self.p_hidden) * without.astype(np.float32)
        return np.round(mixed).astype(np.uint8)

    def shown_hypotheses(self) -> tuple[list[tuple[str, np.ndarray]], list[str]]:
        """The hypotheses that draw differently from the mean and from each heavier one, masked
        (`masked`), and the names of those left out as looking the same."""
        shown, same, seen = [], [], [self.hidden_object]
        for label, frames in self.hypotheses:
            if any(look_alike(frames, other) for other in seen):
                same.append(label.split(":")[0])
            else:
                shown.append((label, masked(frames)))
                seen.append(frames)
        return shown, same

    def figure_rows(self) -> list[tuple[str, str, np.ndarray]]:
        rows = [("observed", "observed", self.observed)]
        two = self.two_objects is not None
        if not two or 1.0 - self.p_two > DRAW_THRESHOLD:
            label = (f"behind the wall,\none object, not two\nidentical ones:\np(one object) = {1.0 - self.p_two:.2f}"
                     if two else "behind the wall")
            rows.append(("behind the wall", label, self._story(self.behind_wall, self.behind_empty)))
        if two and self.p_two > DRAW_THRESHOLD:
            rows.append(("two objects", f"behind the wall, two\nidentical objects:\np(two objects) = {self.p_two:.2f}"
                                        f"\n(the second drawn from\nframe {self.twin_from}, where it is seen)",
                         self._story(self.two_objects, self.two_objects_empty)))
        if self.believed:
            label = (f"hidden object alone,\nif it exists: mean\nof the {self.holding} samples\n"
                     f"holding one\n(their ESS {self.holding_ess:.1f})")
            rows.append(("hidden object", label, masked(self.hidden_object)))
            rows += [("hypothesis", label, frames) for label, frames in self.shown_hypotheses()[0]]
        return rows

    def notes(self) -> list[str]:
        if not self.believed:
            return [f"no hidden object: p(hidden object) = {self.p_hidden:.2f}"]
        stories = sum(kind in ("behind the wall", "two objects") for kind, _, _ in self.figure_rows())
        rows = "rows behind the wall draw" if stories > 1 else "row behind the wall draws"
        lines = [f"p(hidden object) = {self.p_hidden:.2f}: the {rows} it at that opacity"]
        same = self.shown_hypotheses()[1]
        if same:
            lines.append(f"{', '.join(same)}: drawn as the mean or a heavier hypothesis, not shown again")
        return lines


def explain_nll(scorer: Scorer, data: str, index: int, particles: int | None = None, seed: int = 0,
                hypotheses: int = 3, chunk: EncodedChunk | None = None) -> NLLExplanation:
    """What `xvoe explain --surprise nll` draws: the Pyro model's explanation posterior; `chunk`:
    the video's chunk already encoded (`encode_chunk`), where the caller explains several of it."""
    if not scorer.is_random and (scorer.xpl is None or not scorer.xpl.config.use_reasoning):
        raise XvoeError(f"the NLL explanation needs an XPL model with reasoning; {scorer.name} has none")
    config = scorer.nll or InferenceConfig()
    check_particles(particles or config.particles)
    video, rgbd, title = read_video_to_explain(scorer, data, index, chunk)
    return nll_explanation(scorer.vae, scorer.xpl, video, particles or config.particles, title, rgbd, seed,
                           hypotheses, config)


@torch.no_grad()
def nll_explanation(vae, xpl, video: dict, particles: int, title: str = "", observed: np.ndarray | None = None,
                    seed: int = 0, hypotheses: int = 3, config: InferenceConfig | None = None) -> NLLExplanation:
    """The explanation posterior of one encoded video (`encode_video`, a batch of one): the
    weighted mean of the final particles that hold a hidden object, decoded frame by
    frame. The mean, not the best particle: where one particle takes all the weight (a broad
    proposal) the two are the same, and where many share it the mean does not hang on one
    lucky draw; the ESS among them, in the row's label, tells which case it is. Below it, the
    `hypotheses` heaviest distinct trajectories, each decoded alone with its weight, and the
    frames where they disagree most in the title.

    The samples come from `seed`, without touching the global random state; `config`: the
    model's NLL settings (default: InferenceConfig's), `particles` replacing its count."""
    one = {name: value[0] for name, value in video.items()}
    found = explain_surprise(vae, xpl, one["frames"], one["mean"], one["visible"], one["background"],
                             one["occluder"], replace(config or InferenceConfig(), particles=particles), seed=seed,
                             top=hypotheses)
    result = found.result
    posterior = hidden_posterior(result)
    refined = xpl.refine(video["mean"], video["visible"], video["occluder"])
    occupied = video["visible"].any(dim=1)
    slot = result.hidden_slot if posterior is not None else -1

    def with_hidden(latents: torch.Tensor, present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        latents, present = latents.clone(), present.clone()
        latents[0, :, slot], present[0, slot] = posterior.mean, True
        return latents, present

    empty, alone = scene_pictures(vae, refined, occupied, video, -1)
    behind = empty
    if slot >= 0:
        behind, alone = scene_pictures(vae, *with_hidden(refined, occupied), video, slot)
    two = two_object_pictures(vae, refined, video, result.identity, with_hidden if slot >= 0 else None)
    observed = to_uint8(video["frames"][0]).numpy() if observed is None else observed
    heading = f"{title}\n" if title else ""
    heading += f"NLL {result.nll:.0f} nats, p(hidden object) = {result.p_hidden:.2f}"
    if result.identity is not None:
        heading += f", p(two identical objects) = {result.p_two:.2f}"
    if result.estimate.particles == 0:     # the existence head all but ruled one out (inference.evidence.hidden_runs)
        heading += "\nno run with a hidden object: XPL's existence head all but rules one out"
    elif result.estimate.particles < particles:     # a pilot run sufficed: say so
        heading += f"\nfrom a pilot run: {result.estimate.particles} of the {particles:,} particles asked"
    holding = (posterior.holding, posterior.ess) if posterior is not None else (0, 0.0)
    drawn = []
    if posterior is not None and found.hypotheses is not None:
        options = found.hypotheses
        for rank, (trajectory, weight, version) in enumerate(zip(options.trajectories, options.weights,
                                                                 options.version)):
            picture = to_uint8(vae.decode(trajectory.to(video["mean"].dtype))).numpy()
            seen = "\n(with two identical\nobjects seen)" if int(version) else ""
            # its weight given an object: the heading gives p(hidden object), the label which explanation
            drawn.append((f"hypothesis {rank + 1}:\n{float(weight):.2f} of the weight\nof samples holding\n"
                          f"an object{seen}", picture))
        if result.p_hidden > DRAW_THRESHOLD:     # the ESS that matters for a hidden object: among those holding one
            heading += f"\nESS {posterior.ess:.1f} of the {posterior.holding} samples holding an object"
            # the two explanations each draw their own particles: the samples are counted over both
            if result.identity is not None:
                heading += (f" (drawn {result.estimate.particles} for each explanation: one object, two identical "
                            "ones)")
            if options.disagree:
                frames = options.disagree[:3]
                heading += (f"; the hypotheses' latents differ most at frame{'s' if len(frames) > 1 else ''} "
                            f"{', '.join(map(str, frames))}")
    return NLLExplanation(observed, behind, alone, result.hidden_slot, heading, result.p_hidden, result.p_two,
                          result.ess, result.nll, result.estimate.particles, *holding, drawn,
                          behind_empty=empty if slot >= 0 else None, **two)


def two_object_pictures(vae, refined: torch.Tensor, video: dict, identity, with_hidden=None) -> dict:
    """The scene behind the wall under the two-object explanation (`inference.identity`): the
    seen object's first self staying where it went out of sight, and its twin, which the model
    has wait where Transformer 1 filled in the last unseen frame. That fill may stand anywhere
    along the one object's path (in continuity S2, beside the window it was not seen in), so
    the twin is drawn only from the frame it is seen in. `with_hidden` adds the hidden object
    to latents and occupancy (None: there is none). Fields of `NLLExplanation`, none without an
    identity."""
    if identity is None:
        return {}
    latents, seen = two_objects(refined[0], video["visible"][0], identity)
    latents, present = latents[None], seen.any(0)[None]
    first_only = present.clone()
    first_only[0, identity.slot] = False

    def draw(latents: torch.Tensor, present: torch.Tensor, first_only: torch.Tensor) -> np.ndarray:
        both, _ = scene_pictures(vae, latents, present, video, -1)
        before, _ = scene_pictures(vae, latents, first_only, video, -1)
        both[:identity.seen_again] = before[:identity.seen_again]
        return both

    empty = draw(latents, present, first_only)
    if with_hidden is None:
        return {"two_objects": empty, "twin_from": identity.seen_again}
    hidden_latents, hidden_present = with_hidden(latents, present)
    _, hidden_first = with_hidden(latents, first_only)
    return {"two_objects": draw(hidden_latents, hidden_present, hidden_first), "two_objects_empty": empty,
            "twin_from": identity.seen_again}
