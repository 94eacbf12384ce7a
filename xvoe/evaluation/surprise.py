"""Surprise of test videos under a trained model: the paper's MSE score, per frame.

    s_img(t) = sum over pixels (frame_t - composite of the decoded refined latents)^2
    s_dyn(t) = sum over pixels (composite of refined latents - composite of the dynamics'
               prediction)^2,  t >= 1, the occluder's slot left out of both composites

The excess score leaves out what no explanation can change. For a seen object the refined
latents are the encoder's, so the perception module's own reconstruction error of the seen
objects (s_rec, the composite of the seen entries alone) is in s_img whatever the model
believes, and it varies with a scene's clutter and colours far more than an impossible event
moves the score. excess(t) = s_img(t) - s_rec(t) + s_dyn(t) keeps the pixels the fills and the
explanation get wrong, and the dynamics term. Same decodes, one more composite.

Refined latents: Transformer 1 fills the frames in which a seen object is occluded and
Transformer 2 proposes the object seen in no frame. The paper scores every video under that
proposal; `explanation="better"` treats it as one explanation of two and scores a video under
whichever leaves the smaller sum over frames, the proposal or the slot left empty, so that an
object proposed where nothing is hidden costs nothing (docs/decisions.md, "The better of two
explanations"). Decoding is the cost, so only occupied slots are decoded (seen at some frame, or
the explained one), the decodes are shared by the two terms and the two explanations, and videos
are scored in batches with no Python loop over frames. What is drawn (`DrawnScene`) is handed on
to the NLL's scene of the same videos (inference.surprise._hidden_object_scene).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..models.perception import ComponentVAE
from ..models.slots import behind_walls, composite, decode_slots, scene_layers
from ..models.xpl import XPL
from .metrics import excess

__all__ = ["PROPOSED", "BETTER", "EXPLANATIONS", "Surprise", "explained_latents", "DrawnScene", "draw_scene",
           "mse_surprise", "every_explanation", "dynamics_composites", "aggregate"]

# the MSE score's explanations: Transformer 2's proposal always (the paper's), or the better of it and nothing hidden
PROPOSED, BETTER = "proposal", "better"
EXPLANATIONS = (PROPOSED, BETTER)


@dataclass
class Surprise:
    s_img: Tensor        # (B, T)
    s_dyn: Tensor        # (B, T); 0 at frame 0
    s_rec: Tensor        # (B, T) the perception's own error: the seen entries alone composited
    explained_slot: Tensor   # (B,) the slot Transformer 2 filled, -1 if none

    @property
    def per_frame(self) -> Tensor:
        return self.s_img + self.s_dyn

    @property
    def excess(self) -> Tensor:
        return excess(self.s_img, self.s_dyn, self.s_rec)


def explained_latents(xpl: XPL, mean: Tensor, visible: Tensor, occluder: Tensor,
                      kept: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Transformer 1's refined latents with Transformer 2's explanation filled in, the slot it
    filled (B,) (-1 if none, or without reasoning), and the occupied slots (B, K): seen at some
    frame, or explained. `kept` (B,) bool: the videos whose proposal is kept (default: all)."""
    refined = xpl.refine(mean, visible, occluder)
    slot = torch.full(mean.shape[:1], -1, dtype=torch.long, device=mean.device)
    if xpl.config.use_reasoning:
        explained, _, slot = xpl.explain(refined, visible)
        if kept is not None:
            explained = torch.where(kept[:, None, None, None], explained, refined)
            slot = torch.where(kept, slot, -1)
        refined = explained
    return refined, slot, _occupied_slots(visible, slot)


@dataclass
class DrawnScene:
    """A batch of videos as XPL explains them, drawn once: what both explanations of the MSE
    score and the NLL's scene (inference.surprise._hidden_object_scene) read, so that neither
    refines, proposes nor decodes again."""

    refined: Tensor      # (B, T, K, D) Transformer 1's latents
    proposal: Tensor     # (B, T, K, D) with Transformer 2's proposal in `slot`
    scale: Tensor        # (B, T, K, D) Transformer 2's scales, 0 outside `slot`
    slot: Tensor         # (B,) the proposed slot, -1 if none (or without reasoning)
    background: Tensor   # (B, T, 4, H, W) the background component's pictures
    layers: Tensor       # (B, T, K, 4, H, W) the proposal's `scene_layers`: the seen slots (and the proposed one)
    walls: Tensor        # (B, T, 1, 1, H, W) the nearest wall's depth

    def seen_layers(self, blank: Tensor) -> Tensor:
        """The `scene_layers` of what was seen alone: the proposed slot left `blank` (4, H, W).
        It was never seen, so it draws no wall: the walls and every other picture stay as they are."""
        proposed = torch.arange(self.layers.shape[2], device=self.slot.device) == self.slot[:, None]
        return torch.where(proposed[:, None, :, None, None, None], blank, self.layers)

    def video(self, index: int) -> DrawnScene:
        """Video `index` alone, a batch of one."""
        return self._map(lambda tensor: tensor[index:index + 1])

    def full_precision(self) -> DrawnScene:
        """In float32: pictures drawn under bfloat16 autocast come out in bfloat16."""
        return self._map(lambda tensor: tensor.float() if tensor.is_floating_point() else tensor)

    def _map(self, change: Callable[[Tensor], Tensor]) -> DrawnScene:
        return DrawnScene(*(change(getattr(self, field.name)) for field in fields(self)))


@torch.no_grad()
def draw_scene(vae: ComponentVAE, xpl: XPL, mean: Tensor, visible: Tensor, background: Tensor,
               occluder: Tensor, proposed: bool = True) -> DrawnScene:
    """Refine, propose and decode a batch (arguments as `mse_surprise`'s): the background and
    the seen slots, and the proposed slot unless `proposed` is False (the NLL's own drawing)."""
    background_pictures = _decode_background(vae, background)
    refined = xpl.refine(mean, visible, occluder)
    if xpl.config.use_reasoning:
        proposal, scale, slot = xpl.explain(refined, visible)
    else:
        none = torch.full(mean.shape[:1], -1, dtype=torch.long, device=mean.device)
        proposal, scale, slot = refined, torch.zeros_like(refined), none
    drawn = _occupied_slots(visible, slot) if proposed else visible.any(dim=1)
    layers, walls = scene_layers(vae, proposal, drawn, visible, occluder)
    return DrawnScene(refined, proposal, scale, slot, background_pictures, layers, walls)


def _occupied_slots(visible: Tensor, slot: Tensor) -> Tensor:
    """The slots (B, K) seen at some frame, and the explained one (-1: none)."""
    occupied = visible.any(dim=1)
    occupied[torch.arange(len(slot), device=slot.device)[slot >= 0], slot[slot >= 0]] = True
    return occupied


@torch.no_grad()
def mse_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor,
                 background: Tensor, occluder: Tensor, explanation: str = PROPOSED) -> Surprise:
    """frames: (B, T, 4, H, W) in [-1, 1]; mean: (B, T, K, D) posterior means; visible:
    (B, T, K) bool; background: (B, T, D) the background component's means; occluder: (B, K)
    bool, the wall slots. `explanation`: "proposal" (Transformer 2's, the paper's) or "better"
    (the better of it and no hidden object)."""
    if explanation not in EXPLANATIONS:
        raise ValueError(f"explanation must be one of {', '.join(EXPLANATIONS)}, not {explanation!r}")
    scene = draw_scene(vae, xpl, mean, visible, background, occluder)
    return _explanations(vae, xpl, frames, visible, occluder, scene, explanation == BETTER)[explanation]


@torch.no_grad()
def every_explanation(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor,
                      background: Tensor, occluder: Tensor) -> tuple[dict[str, Surprise], DrawnScene]:
    """`mse_surprise` under each of EXPLANATIONS, from one drawing of the batch (`draw_scene`),
    and that drawing, for the NLL to read rather than draw again."""
    scene = draw_scene(vae, xpl, mean, visible, background, occluder)
    return _explanations(vae, xpl, frames, visible, occluder, scene, True), scene


def _explanations(vae: ComponentVAE, xpl: XPL, frames: Tensor, visible: Tensor, occluder: Tensor, scene: DrawnScene,
                  better: bool) -> dict[str, Surprise]:
    """The surprise under Transformer 2's proposal of the batch `scene` draws, and with `better`
    under the better of it and nothing hidden too, by explanation."""
    slot, occupied = scene.slot, _occupied_slots(visible, scene.slot)
    proposed = Surprise(*_terms(vae, xpl, frames, scene.background, scene.proposal, scene.layers, scene.walls,
                                occupied, visible, occluder), slot)
    if not better:
        return {PROPOSED: proposed}
    if not (slot >= 0).any():       # nothing proposed: one explanation
        return {PROPOSED: proposed, BETTER: proposed}
    # the same scene with the proposed slot empty: the other slots' pictures are the same, so only
    # the dynamics' prediction is decoded again
    empty = Surprise(*_terms(vae, xpl, frames, scene.background, scene.refined, scene.seen_layers(vae.blank()[0]),
                             scene.walls, visible.any(dim=1), visible, occluder), torch.full_like(slot, -1))
    return {PROPOSED: proposed, BETTER: _better_explanation(empty, proposed)}


def _better_explanation(first: Surprise, second: Surprise) -> Surprise:
    """Per video, the surprise under whichever explanation leaves the smaller sum over frames
    (the first on a tie)."""
    second_wins = (second.s_img + second.s_dyn).sum(1) < (first.s_img + first.s_dyn).sum(1)

    def pick(a: Tensor, b: Tensor) -> Tensor:
        return torch.where(second_wins.view(-1, *[1] * (a.dim() - 1)), b, a)

    return Surprise(pick(first.s_img, second.s_img), pick(first.s_dyn, second.s_dyn),
                    pick(first.s_rec, second.s_rec), pick(first.explained_slot, second.explained_slot))


@torch.no_grad()
def _latent_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, refined: Tensor, occupied: Tensor, visible: Tensor,
                    background: Tensor, occluder: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """s_img, s_dyn and s_rec (B, T) of given refined latents (B, T, K, D) with occupied slots (B, K),
    as `mse_surprise` scores each explanation: any latents, e.g. the hidden objects' true ones."""
    background_pictures = _decode_background(vae, background)
    layers, walls = scene_layers(vae, refined, occupied, visible, occluder)
    return _terms(vae, xpl, frames, background_pictures, refined, layers, walls, occupied, visible, occluder)


def _decode_background(vae: ComponentVAE, background: Tensor) -> Tensor:
    """The background component's pictures (B, T, 4, H, W) of its means (B, T, D)."""
    return vae.decode(background.flatten(0, 1)).unflatten(0, background.shape[:2])


def _terms(vae: ComponentVAE, xpl: XPL, frames: Tensor, background_pictures: Tensor, refined: Tensor, layers: Tensor,
           walls: Tensor, occupied: Tensor, visible: Tensor, occluder: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """s_img, s_dyn and s_rec (B, T) of refined latents whose `scene_layers` are decoded already."""
    seen, expected = dynamics_composites(vae, xpl, refined, layers, walls, occupied, visible, occluder,
                                         background_pictures)
    s_img = (frames - composite(vae, background_pictures, layers, occupied)).pow(2).flatten(2).sum(2)
    seen_layers = torch.where(visible[..., None, None, None], layers, vae.blank()[0])
    s_rec = (frames - composite(vae, background_pictures, seen_layers, occupied)).pow(2).flatten(2).sum(2)
    s_dyn = torch.zeros_like(s_img)
    s_dyn[:, 1:] = (seen - expected).pow(2).flatten(2).sum(2)
    return s_img, s_dyn, s_rec


def dynamics_composites(vae: ComponentVAE, xpl: XPL, refined: Tensor, layers: Tensor, walls: Tensor,
                        occupied: Tensor, visible: Tensor, occluder: Tensor,
                        background_pictures: Tensor) -> tuple[Tensor, Tensor]:
    """The two pictures s_dyn compares, frames 1..T-1 (B, T-1, 4, H, W): the moving slots'
    `scene_layers` (`layers`, `walls`) composited, and the dynamics' prediction of them, each
    behind the walls it was not seen in front of; the walls themselves left out of both."""
    moving = occupied & ~occluder
    predicted = xpl.predict(refined, occluder)
    predicted_layers = behind_walls(decode_slots(vae, predicted, moving), visible[:, 1:], occluder, walls[:, 1:])
    seen = composite(vae, background_pictures[:, 1:], layers[:, 1:], moving)
    return seen, composite(vae, background_pictures[:, 1:], predicted_layers, moving)


def aggregate(per_frame: Tensor, how: str) -> Tensor:
    """One score per video from per-frame surprise (B, T): the sum (the paper) or the max."""
    if how == "sum":
        return per_frame.sum(dim=1)
    if how == "max":
        return per_frame.max(dim=1).values
    raise ValueError(f"aggregate must be 'sum' or 'max', not {how!r}")
