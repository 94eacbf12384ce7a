"""What the Pyro model believes is behind the wall: the importance-weighted hidden object,
with the posterior probability that it exists and the effective sample size of the weights,
and, where a seen object went out of sight and came back, the two identical objects that may
explain it, with their probability."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

from xvoe.errors import XvoeError
from xvoe.evaluation.explain import Explanation, _pictures, _read_video
from xvoe.evaluation.score import Scorer
from xvoe.models.perception import to_uint8

from .identity import two_objects
from .model import InferenceConfig
from .surprise import explain_surprise, hidden_posterior


@dataclass
class NLLExplanation(Explanation):
    p_hidden: float = 0.0       # posterior probability that a hidden object exists
    p_two: float = 0.0          # posterior probability that a seen object is two identical ones
    ess: float = 0.0            # effective sample size of the importance weights
    nll: float = 0.0            # the video's surprise, -log p(video), nats
    particles: int = 0          # importance samples drawn
    holding: int = 0            # of them, those that held a hidden object
    holding_ess: float = 0.0    # the effective sample size among those
    # the heaviest distinct hypotheses of what is hidden, each decoded alone: (label, frames)
    hypotheses: list[tuple[str, np.ndarray]] = field(default_factory=list)

    def rows(self) -> list[tuple[str, np.ndarray]]:
        if self.holding == 0:
            label = "nothing hidden" if self.slot < 0 else "no sample held one"
        else:
            label = f"if it exists:\nmean of {self.holding} samples\n(ESS {self.holding_ess:.1f})"
        behind = "behind the wall" if self.holding == 0 else "behind the wall,\nif it exists"
        return [("observed", self.observed), (behind, self.behind_wall), (label, self.hidden_object),
                *self.hypotheses]


def explain_nll(scorer: Scorer, data: str, index: int, particles: int | None = None, seed: int = 0,
                hypotheses: int = 3) -> NLLExplanation:
    """What `xvoe explain --surprise nll` draws: the Pyro model's explanation posterior."""
    if not scorer.is_random and (scorer.xpl is None or not scorer.xpl.config.use_reasoning):
        raise XvoeError(f"the NLL explanation needs an XPL model with reasoning; {scorer.name} has none")
    video, rgbd, title = _read_video(scorer, data, index)
    config = scorer.nll or InferenceConfig()
    return nll_explanation(scorer.vae, scorer.xpl, video, particles or config.particles, title, rgbd, seed,
                           hypotheses, config)


@torch.no_grad()
def nll_explanation(vae, xpl, video: dict, particles: int, title: str = "", observed: np.ndarray | None = None,
                    seed: int = 0, hypotheses: int = 3, config: InferenceConfig | None = None) -> NLLExplanation:
    """The explanation posterior of one encoded video (`encode_videos` of one video): the
    importance-weighted mean of the particles that hold a hidden object, decoded frame by
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
    drawn = [] if result.identity is None else [two_object_row(vae, refined, video, result)]
    occupied = video["visible"].any(dim=1)
    slot = result.hidden_slot if posterior is not None else -1
    if posterior is not None:
        refined[0, :, slot] = posterior.mean
        occupied[0, slot] = True
    behind, alone = _pictures(vae, refined, occupied, video, slot)
    observed = to_uint8(video["frames"][0]).numpy() if observed is None else observed
    heading = f"{title}\n" if title else ""
    heading += (f"NLL {result.nll:.0f} nats, p(hidden object) = {result.p_hidden:.2f}, "
                f"ESS {result.ess:.1f} of {particles}")
    if result.identity is not None:
        heading += f", p(two objects) = {result.p_two:.2f}"
    holding = (posterior.holding, posterior.ess) if posterior is not None else (0, 0.0)
    if posterior is not None and found.hypotheses is not None:
        options = found.hypotheses
        for rank, (trajectory, weight, version) in enumerate(zip(options.trajectories, options.weights,
                                                                 options.version)):
            picture = to_uint8(vae.decode(trajectory.to(video["mean"].dtype))).numpy()
            seen = "\nwith two objects" if int(version) else ""
            # its weight given an object: the heading gives p(hidden object), the label which explanation
            drawn.append((f"hypothesis {rank + 1}:\nweight {float(weight):.2f}\nif one is hidden{seen}", picture))
        if options.disagree:
            heading += f"\nthe hypotheses differ most at frames {', '.join(map(str, options.disagree[:3]))}"
    return NLLExplanation(observed, behind, alone, result.hidden_slot, heading, result.p_hidden, result.p_two,
                          result.ess, result.nll, particles, *holding, drawn)


def two_object_row(vae, refined: torch.Tensor, video: dict, result) -> tuple[str, np.ndarray]:
    """The scene behind the wall under the two-object explanation (`inference.identity`): the
    seen object's first self staying where it went out of sight, its twin waiting where it came
    back, with the explanation's posterior probability."""
    latents, seen = two_objects(refined[0], video["visible"][0], result.identity)
    both, _ = _pictures(vae, latents[None], seen.any(0)[None], video, -1)
    return f"two identical objects:\np = {result.p_two:.2f}", both
