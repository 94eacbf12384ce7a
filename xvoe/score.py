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
Transformer 2 proposes the object seen in no frame. Decoding is the cost, so only occupied
slots are decoded (seen at some frame, or the explained one), the decodes are shared by the
two terms, and videos are scored in batches with no Python loop over frames.

The PhyDNet baseline predicts pixels, not latents: its per-frame surprise is the squared
error of its one-step prediction summed over pixels (0 at frame 0). It is written in the
s_dyn column and curve; s_img is all zeros for it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from .metrics import excess
from .models.perception import ComponentVAE
from .models.phydnet import PhyDNet
from .models.xpl import XPL
from .render import DEPTH_FAR, OBJECT_DEPTH, WALL_DEPTH

if TYPE_CHECKING:       # xvoe imports inference only inside the functions that need it
    import numpy as np

    from inference.model import InferenceConfig


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


def decode_slots(vae: ComponentVAE, z: Tensor, occupied: Tensor) -> Tensor:
    """Pictures (B, T, K, 4, H, W) of the latents z (B, T, K, D); unoccupied slots (B, K) are
    left blank (they lose every z-buffer comparison) without running the decoder."""
    batch, frames, slots, _ = z.shape
    blank = vae.blank()[0]
    layers = blank.expand(batch, frames, slots, *blank.shape).clone()
    chosen = occupied[:, None, :].expand(batch, frames, slots)
    if chosen.any():
        layers[chosen] = vae.decode(z[chosen])
    return layers


def composite(vae: ComponentVAE, background: Tensor, layers: Tensor, include: Tensor) -> Tensor:
    """Frames (B, T, 4, H, W) from the background (B, T, 4, H, W) and the slot pictures of
    `include` (B, K) slots; the others are blanked out."""
    blank = vae.blank()[0]
    kept = torch.where(include[:, None, :, None, None, None], layers, blank)
    return vae.composite(torch.cat([background[:, :, None], kept], dim=2))


def explained_latents(xpl: XPL, mean: Tensor, visible: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Transformer 1's refined latents with Transformer 2's explanation filled in, the slot it
    filled (B,) (-1 if none, or without reasoning), and the occupied slots (B, K): seen at some
    frame, or explained."""
    refined = xpl.refine(mean, visible)
    slot = torch.full(mean.shape[:1], -1, dtype=torch.long, device=mean.device)
    if xpl.config.use_reasoning:
        refined, _, slot = xpl.explain(refined, visible)
    occupied = visible.any(dim=1)
    occupied[torch.arange(len(slot))[slot >= 0], slot[slot >= 0]] = True
    return refined, slot, occupied


@torch.no_grad()
def mse_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor,
                 background: Tensor, occluder: Tensor) -> Surprise:
    """frames: (B, T, 4, H, W) in [-1, 1]; mean: (B, T, K, D) posterior means; visible:
    (B, T, K) bool; background: (B, T, D) the background component's means; occluder: (B, K)
    bool, the wall slots."""
    refined, slot, occupied = explained_latents(xpl, mean, visible)
    return Surprise(*latent_surprise(vae, xpl, frames, refined, occupied, visible, background, occluder), slot)


@torch.no_grad()
def latent_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, refined: Tensor, occupied: Tensor, visible: Tensor,
                    background: Tensor, occluder: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """s_img, s_dyn and s_rec (B, T) of given refined latents (B, T, K, D) with occupied slots (B, K):
    `mse_surprise` once Transformers 1 and 2 have run. Apart so that other latents can be scored
    the same way (benchmarks/oracle_fills.py: the hidden objects' true latents for the fills)."""
    batch, frames_count = refined.shape[:2]
    background_pictures = vae.decode(background.flatten(0, 1)).reshape(batch, frames_count, *frames.shape[2:])
    layers, walls = scene_layers(vae, refined, occupied, visible, occluder)
    s_img = (frames - composite(vae, background_pictures, layers, occupied)).pow(2).flatten(2).sum(2)
    seen_layers = torch.where(visible[..., None, None, None], layers, vae.blank()[0])
    s_rec = (frames - composite(vae, background_pictures, seen_layers, occupied)).pow(2).flatten(2).sum(2)

    moving = occupied & ~occluder
    predicted = xpl.predict(refined, occluder)
    predicted_layers = behind_walls(decode_slots(vae, predicted, moving), visible[:, 1:], occluder, walls[:, 1:])
    seen = composite(vae, background_pictures[:, 1:], layers[:, 1:], moving)
    expected = composite(vae, background_pictures[:, 1:], predicted_layers, moving)
    s_dyn = torch.zeros_like(s_img)
    s_dyn[:, 1:] = (seen - expected).pow(2).flatten(2).sum(2)
    return s_img, s_dyn, s_rec


def scene_layers(vae: ComponentVAE, refined: Tensor, occupied: Tensor, visible: Tensor,
                 occluder: Tensor) -> tuple[Tensor, Tensor]:
    """The slot pictures (B, T, K, 4, H, W) a video's refined latents draw, and the nearest
    wall's depth (B, T, 1, 1, H, W): a wall is drawn only in the frames in which the encoder saw
    it, and every object it did not see stands behind the walls (`behind_walls`).

    A wall stands in the nearest depth lane, so nothing hides it: unseen, it is out of the
    picture (lowered from above, or lifted away). Transformer 1 fills it there all the same, and
    a fill that draws a wall costs pixels that vary from one video to its partner."""
    layers = decode_slots(vae, refined, occupied)
    unseen_walls = (occluder[:, None, :] & ~visible)[..., None, None, None]
    layers = torch.where(unseen_walls, vae.blank()[0], layers)
    walls = nearest_wall(layers, occluder)
    return behind_walls(layers, visible, occluder, walls), walls


WALL_PIXEL = 0.5    # decoded depth under which a wall's picture covers a pixel ([-1, 1]; walls stand at -0.5)
BEHIND = 2 * (OBJECT_DEPTH - WALL_DEPTH) / DEPTH_FAR    # from a wall to the objects' lane in [-1, 1]: 0.5


def behind_walls(layers: Tensor, visible: Tensor, occluder: Tensor, walls: Tensor | None = None) -> Tensor:
    """Slot pictures (B, T, K, 4, H, W) in which every object the encoder did not see in a
    frame stands behind the walls there (`push_behind`); seen objects and walls are left
    alone. Transformer 1's fill of a hidden object decodes within a few tenths of the wall's
    depth, and the compositor is soft (a fill 0.2 behind still tints the wall by 6%), so
    without this the fills of objects really behind a wall show through it and cost the
    possible videos pixels; a fill where no wall stands still shows. `walls`: their
    `nearest_wall` depth, if already known (default: from `layers`)."""
    walls = nearest_wall(layers, occluder) if walls is None else walls
    hidden = (~visible & ~occluder[:, None, :])[..., None, None, None]
    return torch.where(hidden, push_behind(layers, walls), layers)


def nearest_wall(layers: Tensor, occluder: Tensor) -> Tensor:
    """Depth (B, T, 1, 1, H, W) of the nearest wall's picture at each pixel (inf: no wall) of
    slot pictures (B, T, K, 4, H, W) whose walls are the slots `occluder` (B, K)."""
    far = torch.full_like(layers[:, :, :1, 3:], float("inf"))
    return torch.where(occluder[:, None, :, None, None, None], layers[:, :, :, 3:], far).amin(dim=2, keepdim=True)


def push_behind(pictures: Tensor, walls: Tensor) -> Tensor:
    """Pictures (..., 4, H, W) whose depth is at least the walls' (..., 1, H, W, broadcast)
    plus BEHIND, the distance from the walls to the objects' lane, where a wall covers the pixel."""
    depth = pictures[..., 3:, :, :]
    pushed = torch.where(walls < WALL_PIXEL, torch.maximum(depth, walls + BEHIND), depth)
    return torch.cat([pictures[..., :3, :, :], pushed], dim=-3)


def aggregate(per_frame: Tensor, how: str) -> Tensor:
    """One score per video from per-frame surprise (B, T): the sum (the paper) or the max."""
    if how == "sum":
        return per_frame.sum(dim=1)
    if how == "max":
        return per_frame.max(dim=1).values
    raise ValueError(f"aggregate must be 'sum' or 'max', not {how!r}")


# --- scoring a split file ---------------------------------------------------------------

NLL_COLUMNS = ("nll", "ess", "p_hidden", "nll_excess")
SCORE_COLUMNS = ("index", "model", "scenario", "setting", "pair", "member", "possible", "score", "s_img", "s_dyn")
EXCESS_COLUMNS = ("s_rec", "excess")    # models with a perception module: XPL, its ablation, PLATO
XPL_STAGES = ("xpl", "plato", "xpl-noresidual")
STAGES = (*XPL_STAGES, "phydnet")


@dataclass
class Scorer:
    """A trained model ready to score: the perception module and one dynamics stage, or PhyDNet."""

    name: str
    vae: ComponentVAE | None
    xpl: XPL | None
    seed: int = 0                 # the random agent's scores, and the NLL's importance samples
    phydnet: PhyDNet | None = None

    @property
    def is_random(self) -> bool:
        return self.vae is None and self.phydnet is None

    @property
    def image_size(self) -> int:
        return (self.phydnet or self.vae).config.image_size


def load_scorer(model: str, device: str = "cpu") -> Scorer:
    """`random`, a shipped model's name (xvoe.zoo), a run directory (its xpl.pt), a stage checkpoint (xpl.pt, plato.pt,
    xpl-noresidual.pt with perception.pt beside it; phydnet.pt), or RUN_DIR/STAGE."""
    from .errors import XvoeError
    from .train import load_perception
    from .train_phydnet import load_phydnet
    from .train_xpl import load_xpl

    if model == "random":
        return Scorer("random", None, None)
    from .zoo import SHIPPED, WEIGHTS, shipped_path

    path = Path(model)
    if model in SHIPPED and not path.exists():
        if shipped_path(model) is None:
            raise XvoeError(f"the model {model} is not shipped with this copy of xvoe; train it with xvoe pipeline")
        run_dir, stage = WEIGHTS, model
    elif path.is_file():
        run_dir, stage = path.parent, path.stem
    elif path.name in STAGES and (path.parent / f"{path.name}.pt").is_file():
        run_dir, stage = path.parent, path.name
    else:
        run_dir, stage = path, "xpl"
    if stage not in STAGES:
        raise XvoeError(f"{model} is not a model to score with: give a run directory, one of "
                        f"{', '.join(s + '.pt' for s in STAGES)}, or 'random'")
    if stage == "phydnet":
        return Scorer(stage, None, None, phydnet=load_phydnet(run_dir / "phydnet.pt", device)[0])
    vae, _ = load_perception(run_dir, device)
    xpl, _ = load_xpl(run_dir, stage, device)
    return Scorer(stage, vae, xpl)


def score_split(model: str | Scorer, data: str, out: str, *, how: str = "sum", videos_per_batch: int = 16,
                surprise: str = "mse", particles: int = 64, overwrite: bool = False, progress: bool = True) -> Path:
    """What `xvoe score` does: one CSV row per test video, and the per-frame surprise curves
    (s_img, s_dyn: (N, T); s_rec too for a model with a perception module) in an .npz beside
    it. Models with a perception module also get the columns s_rec and excess (the module
    docstring). With surprise "nll" or "both", the columns nll, ess, p_hidden and nll_excess
    (`reference_nll`) of the Pyro model are added (XPL models only); with "nll", the score
    column is the NLL."""
    import csv

    import numpy as np
    from tqdm.auto import tqdm

    from . import store
    from .data import check_size
    from .errors import XvoeError

    if how not in ("sum", "max"):
        raise XvoeError(f"--aggregate must be sum or max, not {how!r}")
    if surprise not in ("mse", "nll", "both"):
        raise XvoeError(f"--surprise must be mse, nll or both, not {surprise!r}")
    scorer = load_scorer(model) if isinstance(model, str) else model
    with_nll = surprise != "mse"
    if with_nll and (scorer.xpl is None or not scorer.xpl.config.use_reasoning):
        raise XvoeError(f"the NLL surprise needs an XPL model with reasoning; {scorer.name} has none")
    out = Path(out)
    if out.exists() and not overwrite:
        raise XvoeError(f"{out} exists; pass --overwrite to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    with store.open_dataset(data) as file:
        if file.attrs["split"] != "test":
            raise XvoeError(f"{data} is a {file.attrs['split']} split; scores need a test split")
        count, frames_count, size = file["rgbd"].shape[:3]
        labels = {name: (store.strings(file, name) if name in ("scenario", "setting") else file[name][:])
                  for name in ("scenario", "setting", "pair", "member", "possible")}
        curves = np.zeros((3, count, frames_count))     # s_img, s_dyn, s_rec
        nll = np.zeros((count, 3))      # nll, ess, p_hidden (xpl_nll)
        if with_nll:
            from inference.model import InferenceConfig

            nll_config = InferenceConfig(particles=particles)
        if scorer.is_random:
            curves[:2] = np.random.default_rng(scorer.seed).random((2, count, frames_count))
        else:
            check_size(file, scorer.image_size, f"the model {scorer.name}")
            with torch.random.fork_rng(devices=[]):     # the NLL's particles come from the scorer's seed
                torch.manual_seed(scorer.seed)
                for start in tqdm(range(0, count, videos_per_batch), desc=f"score {scorer.name}", unit="batch",
                                  disable=not progress):
                    stop = min(count, start + videos_per_batch)
                    if scorer.phydnet is not None:
                        curves[:2, start:stop] = torch.stack(_phydnet_curves(scorer, file, start, stop)).numpy()
                        continue
                    batch = encode_videos(scorer, file, start, stop)     # once, for both surprises
                    curves[:, start:stop] = torch.stack(_xpl_curves(scorer, batch)).numpy()
                    if with_nll:
                        nll[start:stop] = xpl_nll(scorer, batch, nll_config)
    with_rec = scorer.vae is not None
    if with_nll:
        nll_excess = nll[:, 0] - reference_nll(curves[2], 4 * size * size, nll_config.pixel_sigma)
        nll = np.column_stack([nll, nll_excess])    # the order of NLL_COLUMNS
    s_img, s_dyn, s_rec = (aggregate(torch.from_numpy(c), how).numpy() for c in curves)
    total = aggregate(torch.from_numpy(curves[:2].sum(0)), how).numpy() if surprise != "nll" else nll[:, 0]
    if with_rec:
        excess_score = aggregate(torch.from_numpy(excess(*curves)), how).numpy()
    tmp = out.with_name(f".{out.name}.tmp")
    with open(tmp, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(SCORE_COLUMNS + (EXCESS_COLUMNS if with_rec else ()) + (NLL_COLUMNS if with_nll else ()))
        for i in range(count):
            extra = [float(s_rec[i]), float(excess_score[i])] if with_rec else []
            extra += list(map(float, nll[i])) if with_nll else []
            writer.writerow([i, scorer.name, labels["scenario"][i], labels["setting"][i], int(labels["pair"][i]),
                             int(labels["member"][i]), bool(labels["possible"][i]), float(total[i]),
                             float(s_img[i]), float(s_dyn[i])] + extra)
    named = {"s_img": curves[0], "s_dyn": curves[1]} | ({"s_rec": curves[2]} if with_rec else {})
    np.savez_compressed(out.with_suffix(".curves.npz"), **named)
    tmp.replace(out)
    return out


def reference_nll(s_rec: np.ndarray, pixels: int, sigma: float) -> np.ndarray:
    """-log N(frames | the perception's drawing of what it saw, sigma^2) per video, from its
    s_rec curve (N, T) and the pixels of one frame: the NLL of a reference that draws the seen
    objects and nothing else, under the Pyro model's pixel likelihood. The NLL less this is a
    log-likelihood ratio (nll_excess): the pixels of the seen objects that the perception
    misses, the same under every hypothesis, cancel, as in the excess score."""
    from inference.model import pixel_log_normaliser

    return s_rec.sum(axis=1) / (2 * sigma ** 2) + pixel_log_normaliser(pixels * s_rec.shape[1], sigma)


def encode_videos(scorer: Scorer, file, start: int, stop: int) -> dict[str, Tensor]:
    """Videos [start, stop) of an open test split, encoded: frames, latents, visibility, walls."""
    from . import store
    from .data import visible_threshold
    from .latents import encode_frames
    from .models.perception import normalise

    _, frames_count, size = file["rgbd"].shape[:3]
    rgbd, ids = file["rgbd"][start:stop], file["ids"][start:stop]
    encoded = encode_frames(scorer.vae, rgbd.reshape(-1, size, size, 4), ids.reshape(-1, size, size),
                            file["states"].shape[2])
    shaped = {k: torch.from_numpy(v).reshape(stop - start, frames_count, *v.shape[1:]) for k, v in encoded.items()}
    return {"frames": normalise(torch.from_numpy(rgbd)), "mean": shaped["mean"],
            "visible": shaped["pixels"] > visible_threshold(size), "background": shaped["background_mean"],
            "occluder": torch.from_numpy(store.wall_mask(file, start, stop))}


def _xpl_curves(scorer: Scorer, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
    """s_img, s_dyn and s_rec (B, T) of encoded videos (`encode_videos`) under XPL or PLATO."""
    surprise = mse_surprise(scorer.vae, scorer.xpl, batch["frames"], batch["mean"], batch["visible"],
                            batch["background"], batch["occluder"])
    return surprise.s_img, surprise.s_dyn, surprise.s_rec


def xpl_nll(scorer: Scorer, batch: dict[str, Tensor], config: InferenceConfig) -> list[tuple[float, float, float]]:
    """(nll, ess, p_hidden) of each encoded video (`encode_videos`) under the Pyro hidden-object model."""
    from inference.surprise import nll_surprise

    results = []
    for i in range(len(batch["mean"])):
        found = nll_surprise(scorer.vae, scorer.xpl, batch["frames"][i], batch["mean"][i], batch["visible"][i],
                             batch["background"][i], batch["occluder"][i], config)
        results.append((found.nll, found.ess, found.p_hidden))
    return results


def _phydnet_curves(scorer: Scorer, file, start: int, stop: int) -> tuple[Tensor, Tensor]:
    """Zeros and PhyDNet's one-step pixel error (B, T) of videos [start, stop) of an open test split."""
    from .models.perception import normalise

    error = scorer.phydnet.surprise(normalise(torch.from_numpy(file["rgbd"][start:stop])))
    return torch.zeros_like(error), error
