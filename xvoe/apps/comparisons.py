"""Frames side by side for a comparison: pairs that the two surprise definitions judge
differently, one scene in each setting of its scenario, and a video against a pixel predictor's
one-step predictions.
"""
from __future__ import annotations

from pathlib import Path

import h5py
import matplotlib.pyplot as plt
import numpy as np
import torch

from ..errors import XvoeError
from ..models.devices import device_of
from ..models.perception import normalise, to_uint8
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE, check_display_size, display_video, enlarge
from ..scenes.scenarios import SCENARIOS
from ..scenes.videos import check_index, find_pair
from ..training.phydnet import load_phydnet
from .frames import cell_inches, draw_frame_rows, frame_rows

__all__ = ["pick_examples", "plot_disagreements", "plot_settings", "predicted_frames", "plot_predictions"]


def pick_examples(rows: list[dict], count: int) -> list[dict]:
    """A few rows of `metrics.disagreements`, one setting at a time in turn, the settings that
    hold an impossible member (a right answer) first."""
    by_setting: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        by_setting.setdefault((row["scenario"], row["setting"]), []).append(row)
    queues = sorted(by_setting.values(), key=lambda queue: queue[0]["right"] == "")
    chosen = []
    for depth in range(max((len(q) for q in queues), default=0)):
        chosen += [queue[depth] for queue in queues if depth < len(queue)]
    return chosen[:count]


def plot_disagreements(file: h5py.File, rows: list[dict], examples: int = 4,
                       display_size: int | None = DISPLAY_SIZE) -> plt.Figure:
    """Pairs that the MSE score and the NLL judge differently (rows of
    `metrics.disagreements`): both members' frames, each with both scores; with
    `display_size`, each member's scene at that size above the model's frames."""
    chosen = pick_examples(rows, examples)
    if not chosen:
        raise XvoeError("no pair is judged differently by the two surprise definitions: nothing to draw")
    frames = file["rgbd"].shape[1]
    cell = cell_inches(display_size or file["rgbd"].shape[2])
    per_member = 1 if display_size is None else 2
    fig, axes = plt.subplots(len(chosen), 1, figsize=(max(4.0, frames * cell), (2 * per_member * cell + 0.7)
                                                      * len(chosen)), squeeze=False)
    for ax, row in zip(axes[:, 0], chosen):
        videos, labels = [], []
        for member in (0, 1):
            index = row[f"index_{member}"]
            stored = store.read_frames(file, "rgbd", index)
            # whole numbers: both are sums of hundreds of terms, and a gap of tens must show
            label = (f"member {member} ({'possible' if file['possible'][index] else 'impossible'})\n"
                     f"MSE score {row[f'score_{member}']:.0f}\nNLL {row[f'nll_{member}']:.0f} nats")
            if display_size is None:
                videos.append(stored)
                labels.append(label)
            else:
                videos += [display_video(file, index, display_size).rgbd, enlarge(stored, display_size)]
                labels += [f"{label}:\nscene {display_size}x{display_size}",
                           f"the model's\n{stored.shape[1]}x{stored.shape[2]}"]
        right = f"; right: {row['right']}" if row["right"] else ""
        title = (f"{row['scenario']} {row['setting']} pair {row['pair']}: the score says {row['score_says']}, "
                 f"the NLL says {row['nll_says']}{right}")
        draw_frame_rows(ax, videos, labels, title, marked=int(file["event_frame"][row["index_1"]]))
    fig.tight_layout()
    return fig


def plot_settings(file: h5py.File, scenario: str, pair: int, display_size: int = DISPLAY_SIZE,
                  frames: list[int] | None = None) -> plt.Figure:
    """One scene in each setting of its scenario, for a class: per setting, each member's scene
    at `display_size` with the model's frames under it, the event frame outlined in red;
    `frames`: the frame numbers to show (default all)."""
    check_display_size(display_size)
    if scenario not in SCENARIOS:
        raise XvoeError(f"{scenario!r} is not a scenario of the benchmark; its scenarios: {', '.join(SCENARIOS)}")
    found = [(setting, find_pair(file, scenario, setting, pair)) for setting in SCENARIOS[scenario].SETTINGS]
    count = file["rgbd"].shape[1]
    frames = list(range(count)) if frames is None else frames
    if not frames or not all(0 <= t < count for t in frames):
        raise XvoeError(f"frames must be frame numbers of 0..{count - 1}, not {frames}")
    cell = cell_inches(display_size)
    fig, axes = plt.subplots(len(found), 1, figsize=(max(4.0, len(frames) * cell), len(found) * (4 * cell + 0.4)),
                             squeeze=False)
    for ax, (setting, members) in zip(axes[:, 0], found):
        videos, labels = [], []
        for member, index in enumerate(members):
            stored = store.read_frames(file, "rgbd", index)[frames]
            videos += [display_video(file, index, display_size).rgbd[frames], enlarge(stored, display_size)]
            labels += [f"member {member}\n({'possible' if file['possible'][index] else 'impossible'}):\n"
                       f"scene {display_size}x{display_size}",
                       f"the model's\n{stored.shape[1]}x{stored.shape[2]}"]
        draw_frame_rows(ax, videos, labels, f"{scenario} {setting}, pair {pair}", frames,
                        int(file["event_frame"][members[1]]))
    fig.tight_layout()
    return fig


def predicted_frames(net, rgbd: np.ndarray) -> np.ndarray:
    """PhyDNet's prediction of each frame of one video (T, H, W, 4) uint8 from the frames before
    it, as uint8 of the same shape; frame 0, which nothing predicts, is blank (255)."""

    with torch.no_grad():
        frames = normalise(torch.from_numpy(np.ascontiguousarray(rgbd))[None]).to(device_of(net))
        predicted = to_uint8(net(frames)[0]).numpy()
    return np.concatenate([np.full_like(rgbd[:1], 255), predicted])


def plot_predictions(model, data: str | Path, index: int) -> plt.Figure:
    """Video `index` of a split file and a PhyDNet's one-step predictions under it: where the
    predicted row parts from the observed one is what the model did not expect (its surprise
    per frame, summed over pixels, in the title). `model`: a loaded PhyDNet, or a checkpoint,
    run directory or shipped name that `load_phydnet` takes."""

    net = load_phydnet(model)[0] if isinstance(model, (str, Path)) else model
    with store.open_dataset(data) as file:
        check_index(file, index)
        rgbd = store.read_frames(file, "rgbd", index)
    surprise = net.surprise(normalise(torch.from_numpy(rgbd))[None].to(device_of(net)))[0, 1:]
    per_frame = " ".join(f"{value:.0f}" for value in surprise.tolist())
    return frame_rows([("observed", rgbd), ("predicted", predicted_frames(net, rgbd))],
                      f"video {index}: surprise of frames 1-{len(rgbd) - 1}: {per_frame}")
