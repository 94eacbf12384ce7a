"""How good are the model's explanations? What the paper only shows in pictures, measured.

- hidden_iou (`hidden_explanations`): blocking S2 member 0 holds a cube that is visible in no
  frame; the IoU of the decoded explanation (Transformer 2's never-seen slot) with the cube's
  true silhouette, rasterised from the saved states, frame by frame.
- mae_iou (`mae_iou`): on expected S1 videos, each ball or cube dropped from the input in all
  frames in turn (its slot emptied, as the proposal stage trains: Transformer 1 sees no trace
  of it); the IoU of Transformer 2's reconstruction with its silhouette.
- fill_iou (`hidden_fills`): Transformer 1's fills of the cubes a wall hides after they were seen.
- the perception's ceiling (`perception_iou`) and the dynamics' one-step error (`dynamics_error`).

Every function takes an open split (`store.open_dataset`) and a loaded model (`load_model`).
"""
from __future__ import annotations

import h5py
import numpy as np
import torch

from ..models.reasoning import hide_slot
from ..models.slots import composite, decode_slots
from ..scenes import store
from ..scenes.scenarios import SCENARIOS
from ..scenes.videos import silhouette
from .explain import decoded_mask, iou
from .scorer import Scorer, encode_videos
from .surprise import BETTER, mse_surprise

__all__ = ["pick", "expected_videos", "ground_truth", "hidden_explanations", "hidden_fills", "perception_iou",
           "mae_iou", "dynamics_error", "principal_spread"]


def pick(file: h5py.File, scenario: str, setting: str, member: int, limit: int) -> list[int]:
    """The first `limit` videos of one member of a setting's pairs."""
    chosen = (store.strings(file, "scenario") == scenario) & (store.strings(file, "setting") == setting)
    return [int(i) for i in np.flatnonzero(chosen & (file["member"][:] == member))[:limit]]


def expected_videos(file: h5py.File, pairs: int) -> list[int]:
    """The possible member of the first pairs of every scenario's S1, a quarter of `pairs` each:
    the videos mae_iou and the dynamics' error are measured on."""
    return [i for scenario in SCENARIOS for i in pick(file, scenario, "S1", 0, max(1, pairs // 4))]


def _split_names(file: h5py.File) -> tuple[list[str], list[str]]:
    """The split's object kind names and state column names."""
    return list(file.attrs["kind_names"]), list(file["states"].attrs["state_columns"])


def _video_iou(masks: np.ndarray, truth: np.ndarray) -> float:
    """The mean over frames of the IoU of two stacks of masks (T, H, W)."""
    return float(np.mean([iou(m, g) for m, g in zip(masks, truth)]))


def ground_truth(file: h5py.File, index: int) -> str:
    """"hidden": an object of the video is visible in no frame; "seen": every object is seen
    at some frame."""
    names, columns = _split_names(file)
    visible = store.read_states(file, index)[:, :, columns.index("visible")].max(axis=0)
    objects = [k for k, kind in enumerate(file["kind"][index]) if names[kind] != "none"]
    return "hidden" if any(visible[k] == 0 for k in objects) else "seen"


def _median(values: list) -> float:
    return float(np.median(values)) if values else float("nan")


def _encode(scorer: Scorer, file: h5py.File, index: int) -> dict:
    return encode_videos(scorer, file, index, index + 1)


@torch.no_grad()
def hidden_explanations(scorer: Scorer, file: h5py.File, videos: list[int]) -> dict:
    """The never-seen cube's explanation, frame by frame against its true silhouette: the IoU
    (hidden_iou, and `per_video` for its interval), and why it falls short: how far the decoded
    centre is from the cube's (pixels, median over frames that draw something), how much of
    that lies along the ball's approach (`away_px`, signed: > 0 farther from the ball than the
    cube), the decoded area over the true one (median), the share of frames that draw nothing;
    and Transformer 1's fill of the ball in the frames the wall hides it (`ball_fill_px`: its x
    less the true x, > 0 beyond it, median). Videos without exactly one never-seen cube are
    skipped."""
    names, columns = _split_names(file)
    x = columns.index("x")
    scores, offsets, away, areas, empty, ball_fill, kept = [], [], [], [], [], [], []
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        states = store.read_states(file, index)
        hidden = [k for k, kind in enumerate(kinds) if kind == "cube"
                  and states[:, k, columns.index("visible")].max() == 0]
        if len(hidden) != 1:
            continue
        video = _encode(scorer, file, index)
        refined = scorer.xpl.refine(video["mean"], video["visible"], video["occluder"])
        explained, _, slot = scorer.xpl.explain(refined, video["visible"])
        kept.append(bool(mse_surprise(scorer.vae, scorer.xpl, video["frames"], video["mean"], video["visible"],
                                      video["background"], video["occluder"], BETTER).explained_slot[0] >= 0))
        if slot[0] < 0:
            scores.append(0.0)
            continue
        masks = decoded_mask(scorer.vae.decode(explained[0, :, slot[0]]))
        truth = silhouette(states[:, hidden[0]], columns, "cube", masks.shape[-1])
        scores.append(_video_iou(masks, truth))
        balls = [k for k, kind in enumerate(kinds) if kind == "ball"]
        # +1 where the ball starts right of the cube: "away from the ball" is then -x
        side = np.sign(states[0, balls[0], x] - states[0, hidden[0], x]) if balls else 0.0
        for mask, true in zip(masks, truth):
            empty.append(not mask.any())
            if mask.any() and true.any():
                (my, mx), (ty, tx) = np.argwhere(mask).mean(0), np.argwhere(true).mean(0)
                offsets.append(np.hypot(my - ty, mx - tx))
                away.append(-(mx - tx) * side)
                areas.append(mask.sum() / true.sum())
        if balls:
            ball = balls[0]
            drawn = decoded_mask(scorer.vae.decode(refined[0, :, ball]))
            present = states[:, ball, columns.index("present")] > 0
            for t in np.flatnonzero(~video["visible"][0, :, ball].cpu().numpy() & present):
                if drawn[t].any():     # the centre's x in pixels; states hold x in pixels too
                    ball_fill.append(-(np.argwhere(drawn[t]).mean(0)[1] + 0.5 - states[t, ball, x]) * side)
    return {"iou": float(np.mean(scores)) if scores else float("nan"), "per_video": scores,
            "centre_px": _median(offsets), "away_px": _median(away), "area_ratio": _median(areas),
            "empty_share": float(np.mean(empty)) if empty else float("nan"), "ball_fill_px": _median(ball_fill),
            "kept_share": float(np.mean(kept)) if kept else float("nan"),
            "shown_iou": float(np.mean(np.where(kept, scores, 0.0))) if kept else float("nan")}


@torch.no_grad()
def hidden_fills(scorer: Scorer, file: h5py.File, videos: list[int]) -> dict:
    """Transformer 1's fills of the cubes a wall hides after they were seen (permanence S1,
    expected member: they fall behind it, land, and are shown again), against their true
    silhouettes in the hidden frames: the mean IoU, the decoded centre's offset (pixels,
    median), the offset at the last hidden frame alone, the IoU by frames before the cube is
    seen again, and the share of fills that draw more than three times the cube's area (a fill
    that took on the wall's shape). The MSE score's dynamics term compares the frame after it
    with the prediction from that fill: a fill that is off costs the possible member at the
    reveal, and the impossible one, whose cube never shows again, does not pay it."""
    names, columns = _split_names(file)
    scores, offsets, before_reveal, oversized, worst = [], [], [], [], (0, -1)
    by_distance: dict[int, list[float]] = {}    # frames before the cube is seen again: IoUs
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        states = store.read_states(file, index)
        video = _encode(scorer, file, index)
        refined = scorer.xpl.refine(video["mean"], video["visible"], video["occluder"])
        for k, kind in enumerate(kinds):
            seen = video["visible"][0, :, k].cpu().numpy()
            hidden = ~seen & (states[:, k, columns.index("present")] > 0)
            if kind != "cube" or not seen.any():
                continue
            frames = [t for t in np.flatnonzero(hidden) if seen[:t].any()]     # hidden after it was seen
            if not frames:
                continue
            masks = decoded_mask(scorer.vae.decode(refined[0, frames, k]))
            truth = silhouette(states[frames, k], columns, "cube", masks.shape[-1])
            scores += [iou(m, g) for m, g in zip(masks, truth)]
            for t, mask, true in zip(frames, masks, truth):
                again = np.flatnonzero(seen[t + 1:])
                if len(again):
                    by_distance.setdefault(int(again[0]) + 1, []).append(iou(mask, true))
                if true.any():
                    oversized.append(mask.sum() > 3 * true.sum())
                    worst = max(worst, (mask.sum() / true.sum(), index))
                if mask.any() and true.any():
                    offset = float(np.hypot(*(np.argwhere(mask).mean(0) - np.argwhere(true).mean(0))))
                    offsets.append(offset)
                    if t + 1 < len(seen) and seen[t + 1]:
                        before_reveal.append(offset)
    return {"iou": float(np.mean(scores)) if scores else float("nan"), "centre_px": _median(offsets),
            "before_reveal_px": _median(before_reveal),
            "oversized_share": float(np.mean(oversized)) if oversized else float("nan"),
            "frames": len(scores), "largest": int(worst[1]),
            "before_reveal_iou": {d: (float(np.mean(v)), len(v)) for d, v in sorted(by_distance.items())}}


@torch.no_grad()
def perception_iou(scorer: Scorer, file: h5py.File, videos: list[int]) -> float:
    """The ceiling of any explanation this perception decodes: the IoU of a wholly visible
    cube's own encoded latent, decoded, with its silhouette (all such frames of the videos)."""
    names, columns = _split_names(file)
    scores = []
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        states = store.read_states(file, index)
        cubes = [k for k, kind in enumerate(kinds) if kind == "cube"]
        if not cubes:
            continue
        video = _encode(scorer, file, index)
        for k in cubes:
            frames = np.flatnonzero(states[:, k, columns.index("visible")] >= 0.999)
            if len(frames):
                masks = decoded_mask(scorer.vae.decode(video["mean"][0, frames, k]))
                truth = silhouette(states[frames, k], columns, "cube", masks.shape[-1])
                scores += [iou(m, g) for m, g in zip(masks, truth)]
    return float(np.mean(scores)) if scores else float("nan")


@torch.no_grad()
def mae_iou(scorer: Scorer, file: h5py.File, videos: list[int]) -> list[float]:
    """The IoU of each ball or cube rebuilt by Transformer 2 with its silhouette, one per
    object (mae_iou is their mean)."""
    names, columns = _split_names(file)
    empty = scorer.vae.posterior(scorer.vae.blank())[0][0]      # the encoder's latent of a slot with no pixels
    scores = []
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        video, states = _encode(scorer, file, index), store.read_states(file, index)
        for slot, kind in enumerate(kinds):
            if kind not in ("ball", "cube"):
                continue
            visible, mean = video["visible"].clone(), video["mean"].clone()
            visible[0, :, slot] = False
            mean[0, :, slot] = empty
            refined = scorer.xpl.refine(mean, visible, video["occluder"])
            keep = hide_slot(visible.shape, torch.tensor([slot], device=visible.device))  # all but the dropped slot
            rebuilt, _ = scorer.xpl.transformer2(refined, keep)
            masks = decoded_mask(scorer.vae.decode(rebuilt[0, :, slot]))
            truth = silhouette(states[:, slot], columns, kind, masks.shape[-1])
            scores.append(_video_iou(masks, truth))
    return scores


@torch.no_grad()
def dynamics_error(scorer: Scorer, file: h5py.File, videos: list[int]) -> tuple[float, float, np.ndarray, np.ndarray]:
    """One-step pixel error, the one-step RMS error per latent of the occupied slots (what the
    NLL's motion_sigma was first set at), and the dynamics targets with and without the residual."""
    errors, latent_errors, residual_targets, direct_targets = [], [], [], []
    for index in videos:
        video = _encode(scorer, file, index)
        refined = scorer.xpl.refine(video["mean"], video["visible"], video["occluder"])
        occupied = video["visible"].any(1)
        predicted = scorer.xpl.predict(refined, video["occluder"])
        background = scorer.vae.decode(video["background"][0])[None]
        expected = composite(scorer.vae, background[:, 1:], decode_slots(scorer.vae, predicted, occupied), occupied)
        errors.append(float((expected - video["frames"][:, 1:]).pow(2).mean()))
        latent_errors.append((predicted - refined[:, 1:])[0][:, occupied[0]].pow(2).flatten().cpu().numpy())
        present = occupied[0].cpu().numpy()
        z = refined[0][:, present].cpu().numpy()                       # (T, objects, D)
        residual_targets.append((z[1:] - z[:-1]).reshape(-1, z.shape[-1]))
        direct_targets.append(z[1:].reshape(-1, z.shape[-1]))
    latent_rms = float(np.sqrt(np.concatenate(latent_errors).mean()))
    return float(np.mean(errors)), latent_rms, np.concatenate(residual_targets), np.concatenate(direct_targets)


def principal_spread(targets: np.ndarray, components: int = 10) -> np.ndarray:
    """Standard deviation along the first principal components (the paper's Fig. 5b)."""
    centred = targets - targets.mean(0)
    values = np.linalg.svd(centred, compute_uv=False) / np.sqrt(len(targets) - 1)
    return values[:components]
