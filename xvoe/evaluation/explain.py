"""What the model believes is behind the wall: decoded refined latents of one video.

For each frame: the observed frame; the decoded scene with the occluder's slot left out
(Transformer 1's filled-in objects and Transformer 2's explanation, seen through the wall);
and the explanation object alone (the never-visible slot Transformer 2 proposed, where the MSE
score keeps it: see `Scorer.explanation`).

The NLL's explanation, the Pyro model's posterior, is inference.explain.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..errors import XvoeError
from ..models.perception import to_uint8
from ..models.slots import composite, decode_slots
from ..scenes import store
from ..scenes.videos import check_index, describe
from ..training.data import check_size
from .scorer import EncodedChunk, Scorer, encode_video
from .surprise import PROPOSED, explained_latents, mse_surprise
from .user_models import read_videos, run_model

__all__ = ["DRAW_THRESHOLD", "Explanation", "DrawnExplanation", "explain_drawn", "explain", "read_video_to_explain",
           "scene_pictures", "drawn_pixels", "masked", "look_alike", "decoded_mask", "iou"]

# A hypothesis of the NLL's posterior below this probability is not drawn as the model's belief:
# no outline, no rows of it, one line of text instead; above it, its outline's opacity is its p.
DRAW_THRESHOLD = 0.05


@dataclass
class Explanation:
    observed: np.ndarray        # (T, H, W, 4) uint8
    behind_wall: np.ndarray     # (T, H, W, 4) uint8: the scene without the occluder
    hidden_object: np.ndarray   # (T, H, W, 4) uint8: the explanation alone, on the blank
    slot: int                   # the explained slot, -1 if every slot was seen
    title: str
    # the scene at a display size for a figure (T, S, S, 4) uint8, and where the objects no frame
    # shows stand in it (T, S, S) bool (xvoe.apps.verbs.with_display); keyword-only, so that the
    # subclasses' fields keep their places
    display: np.ndarray | None = field(default=None, kw_only=True)
    true_hidden: np.ndarray | None = field(default=None, kw_only=True)
    # False where the display is the model's frames enlarged (a split not simulated again)
    display_resimulated: bool = field(default=True, kw_only=True)

    @property
    def draws_hidden(self) -> bool:
        """Whether the explained slot draws something: a slot kept yet decoded to (almost) no
        pixels explains nothing, and figures and printouts call it "nothing hidden"."""
        return self.slot >= 0 and _draws_something(self.hidden_object)

    @property
    def p_drawn(self) -> float:
        """The probability with which the model's hidden object is drawn: the MSE score's
        verdict is all or nothing."""
        return 1.0 if self.draws_hidden else 0.0

    def figure_rows(self) -> list[tuple[str, str, np.ndarray]]:
        """What a figure draws: (kind, label, frames) per row; the kind ("observed", "behind the
        wall", "hidden object", "nothing hidden", ...) says what the row shows, the label says it
        in plain words."""
        alone = ("hidden object", "the hidden object\nalone") if self.draws_hidden else ("nothing hidden",
                                                                                       "nothing hidden")
        return [("observed", "observed", self.observed), ("behind the wall", "behind the wall", self.behind_wall),
                (*alone, masked(self.hidden_object))]

    def rows(self) -> list[tuple[str, np.ndarray]]:
        """What a figure draws, one labelled row of frames each."""
        return [(label, frames) for _, label, frames in self.figure_rows()]

    def notes(self) -> list[str]:
        """Lines of text a figure writes under its rows."""
        return []


@dataclass
class DrawnExplanation(Explanation):
    """What a model of your own draws behind the wall (`SurpriseModel.explain`), under the video."""

    @property
    def draws_hidden(self) -> bool:
        return False        # the model's own drawing: which pixels are its hidden object is not known

    def figure_rows(self) -> list[tuple[str, str, np.ndarray]]:
        return [("observed", "observed", self.observed),
                ("drawn", "the model's\nexplanation", self.behind_wall)]


def explain_drawn(scorer: Scorer, data: str, index: int) -> DrawnExplanation:
    """The frames (T, H, W, C >= 3, uint8) a model of your own returns from `explain(videos)`."""
    with store.open_dataset(data) as file:
        check_index(file, index)
        videos, title = read_videos(file, index, index + 1), describe(file, index)
    try:
        drawn = np.asarray(run_model(scorer.custom, "explain", videos, scorer.time_limit))
    except (ValueError, TypeError):
        drawn = np.zeros(0, object)     # ragged, or not an array: refused below with what it is
    expected = videos.rgbd.shape[:4]
    if drawn.shape[:4] != expected or drawn.ndim != 5 or drawn.shape[4] < 3 or drawn.dtype != np.uint8:
        raise XvoeError(f"the model {scorer.name} drew frames of shape {drawn.shape} and type {drawn.dtype}; "
                        f"expected uint8 of shape {(*expected, 'C >= 3')}")
    return DrawnExplanation(videos.rgbd[0], drawn[0], drawn[0], -1, title)


def read_video_to_explain(scorer: Scorer, data: str, index: int,
                chunk: EncodedChunk | None = None) -> tuple[dict, np.ndarray, str]:
    """Video `index` of a split file, encoded for the scorer as its score encodes it, so that an
    explanation is of the score's own latents (read from `chunk` where it holds the video); its
    frames (T, H, W, 4); its title."""
    if scorer.is_random:
        raise XvoeError("the random agent explains nothing; give a trained model")
    with store.open_dataset(data) as file:
        check_index(file, index)
        check_size(file, scorer.vae.config.image_size, f"the model {scorer.name}")
        frames = store.read_frames(file, "rgbd", index)
        video = chunk.video(index) if chunk is not None and chunk.holds(index) else encode_video(scorer, file, index)
        return video, frames, describe(file, index)


def scene_pictures(vae, refined: torch.Tensor, occupied: torch.Tensor, video: dict,
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
def explain(scorer: Scorer, data: str, index: int, chunk: EncodedChunk | None = None) -> Explanation:
    """What the MSE score's explanation puts behind the wall in video `index`; `chunk`: its
    videos already encoded (`encode_chunk`), where the caller explains several of them."""
    video, rgbd, title = read_video_to_explain(scorer, data, index, chunk)
    kept = None     # the explanation the MSE score rests on: with "better", nothing hidden where that fits better
    if scorer.explanation != PROPOSED:
        kept = mse_surprise(scorer.vae, scorer.xpl, video["frames"], video["mean"], video["visible"],
                            video["background"], video["occluder"], scorer.explanation).explained_slot >= 0
    refined, slot, occupied = explained_latents(scorer.xpl, video["mean"], video["visible"], video["occluder"], kept)
    behind, alone = scene_pictures(scorer.vae, refined, occupied, video, int(slot[0]))
    return Explanation(rgbd, behind, alone, int(slot[0]), title)


# --- measuring explanations against the ground truth --------------------------------------

_OBJECT_DEPTH_LIMIT = 0.75   # normalised depth: decoded objects lie near 0, the blank at 1.5


_DRAWN_SHARE = 0.002     # of a frame's pixels: a slot drawing fewer in every frame draws nothing


def drawn_pixels(pictures: np.ndarray) -> np.ndarray:
    """Where decoded uint8 pictures (..., H, W, 4) draw an object (T, H, W) bool."""
    return pictures[..., 3] < (_OBJECT_DEPTH_LIMIT + 1.0) * 127.5       # normalised units to uint8


def masked(pictures: np.ndarray) -> np.ndarray:
    """Decoded uint8 pictures (..., H, W, 4) of one slot white wherever it draws nothing: the
    decoder's colours outside its mask are a haze no composite shows."""
    out = pictures.copy()
    out[~drawn_pixels(pictures)] = 255
    return out


_SAME_PIXELS = 3     # a decoded object differing from another in fewer pixels of every frame looks the same


def _differing_pixels(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per frame, how many pixels two decoded uint8 pictures (T, H, W, 4) of one slot draw
    differently to the eye: drawn by one alone, or by both in colours more than a fifth of the
    colour range apart."""
    drawn_a, drawn_b = drawn_pixels(a), drawn_pixels(b)
    colour = np.abs(a[..., :3].astype(np.int16) - b[..., :3].astype(np.int16)).max(axis=-1) > 51
    return ((drawn_a != drawn_b) | (drawn_a & drawn_b & colour)).sum(axis=(-2, -1))


def look_alike(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two decoded uint8 pictures (T, H, W, 4) of one slot draw the same to the eye:
    fewer than SAME_PIXELS differing pixels (`_differing_pixels`) in every frame."""
    return int(_differing_pixels(a, b).max(initial=0)) < _SAME_PIXELS


def _draws_something(pictures: np.ndarray) -> bool:
    """Whether decoded uint8 pictures (T, H, W, 4) of one slot draw at least DRAWN_SHARE of a
    frame in some frame."""
    drawn = drawn_pixels(pictures)
    return bool(drawn.any()) and float(drawn.mean(axis=(-2, -1)).max()) >= _DRAWN_SHARE


def decoded_mask(pictures: np.ndarray | torch.Tensor) -> np.ndarray:
    """Where a decoded object (..., 4, H, W), in normalised units, draws something."""
    depth = torch.as_tensor(pictures)[..., 3, :, :]
    return (depth < _OBJECT_DEPTH_LIMIT).cpu().numpy()


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks; 1 when both are empty."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
