"""The perception module's goals on held-out frames: reconstruction PSNR and a linear position probe.

- PSNR of the decoded composite (posterior means) against the frame, RGB (the goal: >= 26 dB),
  depth, and RGB on object pixels only; pooled over every frame, with an interval over videos.
- probe: a least-squares map from a visible object's latent mean to its x and y, fitted on the
  first half of the videos and scored (R^2) on the second half, with an interval over the
  held-out videos (the fit fixed). `position_probes` fits one per kind (the goal: >= 0.95 for x
  and y of cubes and walls and x of balls: the kinds code height differently, so one probe for
  all of them mixes codes) and one for every visible object (reported). A ball's y has no goal:
  balls never leave the floor in the generator's splits (only falling cubes do), so it does not
  vary and has no R^2 (docs/decisions.md, "What the goals count").

Held-out means frames the model was not trained on: a train-type split from another seed.
Any split with states works (a test split too): nothing here trains.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..models.devices import device_of
from ..models.perception import ComponentVAE, to_uint8
from ..scenes import store
from ..training.data import check_size, perception_batch, visible_threshold
from ..training.latents import encode_means
from .resampling import interval

__all__ = ["POOLED", "PROBE_GOALS", "HeldOut", "read_held_out", "reconstruction", "latent_positions",
           "PositionProbe", "position_probes", "hidden_part_error"]

_CHANNELS = ("rgb", "depth", "objects")
POOLED = "all"                              # position_probes' key of the probe for every visible object
PROBE_GOALS = {"ball": ("x",), "cube": ("x", "y"), "wall": ("x", "y")}      # the probes' goal lines: kind, axes


@dataclass
class HeldOut:
    """The first videos of a split, as the perception's measures read them."""

    rgbd: np.ndarray        # (V, T, H, W, 4) uint8
    ids: np.ndarray         # (V, T, H, W): the slot each pixel shows
    states: np.ndarray      # (V, T, K, S)
    kind: np.ndarray        # (V, K)
    columns: list[str]      # the state columns
    kind_names: list[str]

    def positions(self) -> np.ndarray:
        """(V, T, K, 2): every slot's x and y in pixels."""
        return self.states[..., [self.columns.index("x"), self.columns.index("y")]]


def read_held_out(data: str | Path, videos: int, image_size: int) -> HeldOut:
    """The first `videos` videos of a split at the model's frame size (refused otherwise)."""
    with store.open_dataset(data) as file:
        check_size(file, image_size, "the perception")
        count = min(videos, file["rgbd"].shape[0])
        return HeldOut(store.read_frames(file, "rgbd", 0, count), store.read_frames(file, "ids", 0, count),
                       store.read_states(file, 0, count), file["kind"][:count],
                       list(file["states"].attrs["state_columns"]), list(file.attrs["kind_names"]))


def _psnr(error_sum: float | np.ndarray, count: float | np.ndarray) -> float | np.ndarray:
    """Peak signal-to-noise ratio (dB) of 8-bit values from a sum of squared errors over `count` values."""
    return 10 * np.log10(255.0 ** 2 / np.maximum(error_sum / np.maximum(count, 1), 1e-12))


def _squared_errors(model: ComponentVAE, held: HeldOut, batch: int = 256) -> dict[str, np.ndarray]:
    """Per video, the summed squared errors of the decoded composites and how many values they
    cover, per channel group (`rgb`, `depth`, `objects`: RGB on object pixels)."""
    videos, frames, size = held.rgbd.shape[:3]
    rgbd, ids = held.rgbd.reshape(-1, size, size, 4), held.ids.reshape(-1, size, size)
    slots = held.states.shape[2]
    sums = {name: np.zeros(len(rgbd)) for name in _CHANNELS}
    counts = {name: np.zeros(len(rgbd)) for name in _CHANNELS}
    for start in range(0, len(rgbd), batch):
        chunk, maps = rgbd[start:start + batch], ids[start:start + batch]
        noise = np.zeros((len(chunk), slots + 1, model.config.latent_dim), np.float32)
        parts = perception_batch(chunk, maps, slots, noise, noise[:1, 0]).to(device_of(model))
        with torch.no_grad():
            drawn = to_uint8(model.forward_batch(parts, sample=False)["composite"]).numpy()
        error = (drawn.astype(np.float64) - chunk) ** 2
        on = (maps > 0)[..., None]
        rows = slice(start, start + len(chunk))
        sums["rgb"][rows] = error[..., :3].sum((1, 2, 3))
        counts["rgb"][rows] = error[0, ..., :3].size
        sums["depth"][rows] = error[..., 3].sum((1, 2))
        counts["depth"][rows] = error[0, ..., 3].size
        sums["objects"][rows] = (error[..., :3] * on).sum((1, 2, 3))
        counts["objects"][rows] = 3 * on.sum((1, 2, 3))
    return {f"{name}_{part}": table[name].reshape(videos, frames).sum(1)
            for part, table in (("sum", sums), ("count", counts)) for name in _CHANNELS}


def reconstruction(model: ComponentVAE, held: HeldOut, rounds: int = 1000,
                   seed: int = 0) -> dict[str, tuple[float, float, float]]:
    """PSNR (dB) per channel group, pooled over all frames: (value, low, high), the interval
    from resampling videos."""
    errors = _squared_errors(model, held)
    return {name: _pooled_psnr(errors[f"{name}_sum"], errors[f"{name}_count"], rounds, seed) for name in _CHANNELS}


def _pooled_psnr(total: np.ndarray, count: np.ndarray, rounds: int, seed: int) -> tuple[float, float, float]:
    """PSNR of per-video error sums pooled, and its interval over videos."""
    low, high = interval(lambda chosen: _psnr(total[chosen].sum(), count[chosen].sum()), len(total), rounds, seed)
    return float(_psnr(total.sum(), count.sum())), low, high


def latent_positions(model: ComponentVAE, held: HeldOut) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latent means (V, T, K, D), true positions (V, T, K, 2), and which slots are visible (V, T, K)."""
    means, pixels = encode_means(model, held.rgbd, held.ids, held.states.shape[2])
    return means, held.positions(), pixels > visible_threshold(held.rgbd.shape[2])


def _fit_probe(means: np.ndarray, targets: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """Least-squares weights (D + 1, targets) from the chosen slots' latent means (with a constant)."""
    weights, *_ = np.linalg.lstsq(np.c_[means[chosen], np.ones(chosen.sum())], targets[chosen], rcond=None)
    return weights


def _r_squared(truth: np.ndarray, guess: np.ndarray) -> np.ndarray:
    """R^2 per column; nan where the truth does not vary."""
    spread = ((truth - truth.mean(0)) ** 2).sum(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(spread > 1e-6 * len(truth), 1 - ((truth - guess) ** 2).sum(0) / spread, np.nan)


def _probe(means: np.ndarray, targets: np.ndarray, chosen: np.ndarray, rounds: int = 0,
          seed: int = 0) -> list[tuple[float, float, float]]:
    """Per target column, (R^2, low, high) of a probe fitted on the first half of the videos and
    scored on the second half, over the `chosen` slots (V, T, K); the interval resamples the
    held-out videos (no interval, nan, when rounds is 0 or the R^2 is nan)."""
    half = len(means) // 2
    weights = _fit_probe(means[:half], targets[:half], chosen[:half])
    held = chosen[half:]
    truth = targets[half:][held]
    guess = np.c_[means[half:][held], np.ones(held.sum())] @ weights
    values = _r_squared(truth, guess)
    video = np.nonzero(held)[0]          # the held-out video of each chosen slot
    return [(float(value), *(_r2_interval(truth[:, c], guess[:, c], video, len(held), rounds, seed)
                             if rounds and np.isfinite(value) else (float("nan"),) * 2))
            for c, value in enumerate(values)]


@dataclass
class PositionProbe:
    """One probe's result: (R^2, low, high) for x and for y, over the visible objects (slots in a
    frame) of the held-out half; nan with a `reason` where it could not be measured."""

    objects: int                    # visible objects of the held-out half
    x: tuple[float, float, float]
    y: tuple[float, float, float]
    reason: str = ""


def position_probes(means: np.ndarray, positions: np.ndarray, visible: np.ndarray, kind: np.ndarray,
                    kind_names: list[str], rounds: int = 0, seed: int = 0) -> dict[str, PositionProbe]:
    """The position probe (`_probe`: same halves, same interval) for every visible object, under
    `POOLED`, and for each kind's visible objects alone, under the kind's name: every kind of
    `kind_names` but "none", and each kind of `PROBE_GOALS` whether the split names it or not.

    means (V, T, K, D), positions (V, T, K, 2), visible (V, T, K), kind (V, K) indexing
    kind_names. A kind is measured when the first half of the videos holds at least D + 1 of its
    visible objects (fewer leave the D + 1 weights of the least-squares fit undetermined) and the
    second half at least 2; else its x and y are nan and `reason` says which half fell short. A
    held-out x or y that does not vary has no R^2: nan, and the reason says so.
    """
    half, needed = len(means) // 2, means.shape[-1] + 1
    kinds = np.broadcast_to(kind[:, None, :], visible.shape)
    groups = {POOLED: visible}
    for name in dict.fromkeys([*(n for n in kind_names if n != "none"), *PROBE_GOALS]):
        groups[name] = visible & (kinds == kind_names.index(name)) if name in kind_names else np.zeros_like(visible)
    found = {}
    for name, chosen in groups.items():
        fitted, held = int(chosen[:half].sum()), int(chosen[half:].sum())
        if fitted < needed or held < 2:
            short = (f"visible objects in the fitting half: {fitted}, fewer than the fit's {needed} weights"
                     if fitted < needed else f"visible objects in the held-out half: {held}, fewer than 2")
            missing = (float("nan"),) * 3
            found[name] = PositionProbe(held, missing, missing, short)
            continue
        r2_x, r2_y = _probe(means, positions, chosen, rounds, seed)
        flat = [axis for axis, value in (("x", r2_x[0]), ("y", r2_y[0])) if np.isnan(value)]
        found[name] = PositionProbe(held, r2_x, r2_y,
                                    f"{' and '.join(flat)} does not vary in the held-out half" if flat else "")
    return found


def _r2_interval(truth: np.ndarray, guess: np.ndarray, video: np.ndarray, videos: int, rounds: int,
                 seed: int) -> tuple[float, float]:
    """The interval of R^2 over videos, from per-video sums (count, sum, sum of squares, squared
    error) that a resample of videos adds up."""
    count = np.bincount(video, minlength=videos)
    total, square, missed = (np.bincount(video, w, videos) for w in (truth, truth ** 2, (truth - guess) ** 2))

    def statistic(chosen: np.ndarray) -> float:
        n = count[chosen].sum()
        spread = square[chosen].sum() - total[chosen].sum() ** 2 / max(n, 1)
        return 1 - missed[chosen].sum() / spread if n and spread > 1e-6 * n else float("nan")

    return interval(statistic, videos, rounds, seed)


def hidden_part_error(means: np.ndarray, targets: np.ndarray, seen: np.ndarray, fraction: np.ndarray,
                      edge: np.ndarray) -> dict[str, tuple[int, np.ndarray]]:
    """RMS error (pixels) of x and y read linearly from the latents, by how much of the object is
    in view: the probe is fitted on wholly visible objects of the first half of the videos and
    applied to the second half's wholly visible ones, the partly hidden ones (behind another
    object) and the ones the frame's edge cuts. A position code that follows the visible part,
    not the object, shows as a larger error in the last two."""
    half = len(means) // 2
    groups = {"whole": seen & (fraction >= 0.99) & ~edge, "partly hidden": seen & (fraction < 0.9) & ~edge,
              "cut by the frame's edge": seen & edge}
    weights = _fit_probe(means[:half], targets[:half], groups["whole"][:half])
    errors = {}
    for name, chosen in groups.items():
        chosen = chosen[half:]
        guess = np.c_[means[half:][chosen], np.ones(chosen.sum())] @ weights
        errors[name] = (int(chosen.sum()), np.sqrt(((guess - targets[half:][chosen]) ** 2).mean(0)))
    return errors
