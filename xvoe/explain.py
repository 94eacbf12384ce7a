"""What the model believes is behind the wall: decoded refined latents of one video.

For each frame: the observed frame; the decoded scene with the occluder's slot left out
(Transformer 1's filled-in objects and Transformer 2's explanation, seen through the wall);
and the explanation object alone (the never-visible slot Transformer 2 proposed).

With the NLL surprise (`explain_nll`) the explanation is the Pyro model's posterior instead:
the importance-weighted hidden object, with the posterior probability that it exists and the
effective sample size of the weights.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from . import store
from .data import check_size
from .errors import XvoeError
from .models.perception import to_uint8
from .score import Scorer, composite, decode_slots, encode_videos, explained_latents
from .viz import check_index, describe


@dataclass
class Explanation:
    observed: np.ndarray        # (T, H, W, 4) uint8
    behind_wall: np.ndarray     # (T, H, W, 4) uint8: the scene without the occluder
    hidden_object: np.ndarray   # (T, H, W, 4) uint8: the explanation alone, on the blank
    slot: int                   # the explained slot, -1 if every slot was seen
    title: str

    def rows(self) -> list[tuple[str, np.ndarray]]:
        """What a figure draws, one labelled row of frames each."""
        return [("observed", self.observed), ("behind the wall", self.behind_wall),
                ("explanation" if self.slot >= 0 else "nothing hidden", self.hidden_object)]


@dataclass
class NLLExplanation(Explanation):
    p_hidden: float = 0.0       # posterior probability that a hidden object exists
    ess: float = 0.0            # effective sample size of the importance weights
    nll: float = 0.0            # the video's surprise, -log p(video), nats
    particles: int = 0          # importance samples drawn
    holding: int = 0            # of them, those that held a hidden object
    holding_ess: float = 0.0    # the effective sample size among those

    def rows(self) -> list[tuple[str, np.ndarray]]:
        if self.holding == 0:
            label = "nothing hidden" if self.slot < 0 else "no sample held one"
        else:
            label = f"if it exists:\nmean of {self.holding} samples\n(ESS {self.holding_ess:.1f})"
        behind = "behind the wall" if self.holding == 0 else "behind the wall,\nif it exists"
        return [("observed", self.observed), (behind, self.behind_wall), (label, self.hidden_object)]


def _read_video(scorer: Scorer, data: str, index: int) -> tuple[dict, np.ndarray, str]:
    """Video `index` of a split file, encoded for the scorer; its frames (T, H, W, 4); its title."""
    if scorer.is_random:
        raise XvoeError("the random agent explains nothing; give a trained model")
    with store.open_dataset(data) as file:
        check_index(file, index)
        check_size(file, scorer.vae.config.image_size, f"the model {scorer.name}")
        return encode_videos(scorer, file, index, index + 1), file["rgbd"][index], describe(file, index)


def _pictures(vae, refined: torch.Tensor, occupied: torch.Tensor, video: dict,
              slot: int) -> tuple[np.ndarray, np.ndarray]:
    """The scene behind the wall (occluder left out) and slot `slot` alone (-1: the blank), uint8."""
    layers = decode_slots(vae, refined, occupied)
    background_pictures = vae.decode(video["background"][0])[None]
    behind = composite(vae, background_pictures, layers, occupied & ~video["occluder"])
    if slot >= 0:
        alone = layers[0, :, slot]
    else:
        alone = vae.blank()[0].expand(refined.shape[1], *layers.shape[-3:])
    return to_uint8(behind[0]).numpy(), to_uint8(alone).numpy()


@torch.no_grad()
def explain(scorer: Scorer, data: str, index: int) -> Explanation:
    video, rgbd, title = _read_video(scorer, data, index)
    refined, slot, occupied = explained_latents(scorer.xpl, video["mean"], video["visible"])
    behind, alone = _pictures(scorer.vae, refined, occupied, video, int(slot[0]))
    return Explanation(rgbd, behind, alone, int(slot[0]), title)


def explain_nll(scorer: Scorer, data: str, index: int, particles: int = 64, seed: int = 0) -> NLLExplanation:
    """What `xvoe explain --surprise nll` draws: the Pyro model's explanation posterior."""
    if not scorer.is_random and (scorer.xpl is None or not scorer.xpl.config.use_reasoning):
        raise XvoeError(f"the NLL explanation needs an XPL model with reasoning; {scorer.name} has none")
    video, rgbd, title = _read_video(scorer, data, index)
    return nll_explanation(scorer.vae, scorer.xpl, video, particles, title, rgbd, seed)


@torch.no_grad()
def nll_explanation(vae, xpl, video: dict, particles: int, title: str = "", observed: np.ndarray | None = None,
                    seed: int = 0) -> NLLExplanation:
    """The explanation posterior of one encoded video (`encode_videos` of one video): the
    importance-weighted mean of the particles that hold a hidden object, decoded frame by
    frame. The mean, not the best particle: where one particle takes all the weight (a broad
    proposal) the two are the same, and where many share it the mean does not hang on one
    lucky draw; the ESS among them, in the row's label, tells which case it is.

    The samples come from `seed`, without touching the global random state. `inference` is
    imported on call, as in score.py: importing xvoe never imports it."""
    from inference.model import InferenceConfig
    from inference.surprise import hidden_posterior, nll_surprise

    one = {name: value[0] for name, value in video.items()}
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        result = nll_surprise(vae, xpl, one["frames"], one["mean"], one["visible"], one["background"],
                              one["occluder"], InferenceConfig(particles=particles))
    posterior = hidden_posterior(result)
    refined = xpl.refine(video["mean"], video["visible"])
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
    holding = (posterior.holding, posterior.ess) if posterior is not None else (0, 0.0)
    return NLLExplanation(observed, behind, alone, result.hidden_slot, heading, result.p_hidden, result.ess,
                          result.nll, particles, *holding)


# --- measuring explanations against the ground truth --------------------------------------

OBJECT_DEPTH_LIMIT = 0.75   # normalised depth: decoded objects lie near 0, the blank at 1.5


def silhouette(states: np.ndarray, columns: list[str], kind: str, size: int) -> np.ndarray:
    """The whole silhouette (T, H, W) of one object from its saved states (T, S), occlusion
    ignored: a disk for a ball, a square for a cube."""
    x, y, half = (states[:, columns.index(c)] for c in ("x", "y", "size"))
    centres = np.arange(size) + 0.5
    dx = centres[None, None, :] - x[:, None, None]
    dy = centres[None, :, None] - y[:, None, None]
    if kind == "ball":
        mask = dx ** 2 + dy ** 2 <= half[:, None, None] ** 2
    else:
        mask = (np.abs(dx) <= half[:, None, None]) & (np.abs(dy) <= half[:, None, None])
    return mask & (states[:, columns.index("present")] > 0)[:, None, None]


def decoded_mask(pictures: np.ndarray | torch.Tensor) -> np.ndarray:
    """Where a decoded object (..., 4, H, W), in normalised units, draws something."""
    depth = torch.as_tensor(pictures)[..., 3, :, :]
    return (depth < OBJECT_DEPTH_LIMIT).numpy()


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks; 1 when both are empty."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
