"""Surprise over frames: a test pair's per-frame curves from a score file, drawn still (each
definition or score term on its own axis) or frame by frame under the pair's scenes.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.animation import FuncAnimation

from ..errors import XvoeError
from ..evaluation.metrics import excess
from ..evaluation.score_curves import read_curves
from ..evaluation.score_headers import check_same_split, warn_unchecked
from ..evaluation.score_tables import read_scores
from ..evaluation.scorer import MSE_LABEL
from ..fingerprints import split_identity
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE, check_display_size, display_video
from ..scenes.videos import find_pair, labels_of, pair_rows, wall_lowered

__all__ = ["PairCurves", "pair_curves", "draw_pair_curves", "member_labels", "plot_surprise_curves",
           "plot_surprise_definitions", "definition_curves", "animate_pair"]


@dataclass
class PairCurves:
    """The saved per-frame curves of a test pair's two members, with what marks their frames."""

    model: str
    curves: dict[str, np.ndarray]   # name -> (2, T): member 0, member 1
    possible: list[bool]
    events: list[int]               # each member's event frame (-1: none, or no split given)
    lowered: np.ndarray             # (T,) how far the wall stands in either member (0 without the split)
    own: str | None = None          # a model's own curve (`xvoe.evaluation.score_curves.Curves`); None: the MSE's terms
    label: str = MSE_LABEL          # what its axis measures


def pair_curves(scores: str | Path, data: str | Path | None, scenario: str, setting: str, pair: int,
                curves: str | Path | None = None, frame: int | None = None) -> PairCurves:
    """The curves of a test pair from a scores CSV and its curves file, checked against the test
    split `data` (None: the curves alone); `frame`, a cursor to draw, checked against them."""
    table = read_scores(scores)
    saved = read_curves(curves if curves is not None else Path(scores).with_suffix(".curves.npz"),
                        len(table["index"]), scores)
    rows = pair_rows(table["scenario"], table["setting"], table["pair"], table["member"], scenario, setting, pair,
                      str(scores))
    videos = [int(table["index"][r]) for r in rows]
    frames = saved.total.shape[1]
    events, lowered = [-1, -1], np.zeros(frames)
    if data is not None:
        with store.open_dataset(data) as file:
            check_same_split(scores, split_identity(file), data)
            warn_unchecked(scores)
            for video in videos:
                if not 0 <= video < file["rgbd"].shape[0] or labels_of(file, video) != (scenario, setting, pair):
                    raise XvoeError(f"{scores} does not match {data}: its video {video} is not {scenario} "
                                    f"{setting} pair {pair} there")
            if file["rgbd"].shape[1] != frames:
                raise XvoeError(f"{data} has {file['rgbd'].shape[1]} frames a video, the curves {frames}")
            events = [int(file["event_frame"][v]) for v in videos]
            lowered = np.maximum(wall_lowered(file, videos[0]), wall_lowered(file, videos[1]))
    if frame is not None and not 0 <= frame < frames:
        raise XvoeError(f"frame {frame} is out of range: the videos have frames 0..{frames - 1}")
    model = str(table["model"][0]) if "model" in table else Path(scores).stem
    return PairCurves(model, {name: values[list(rows)] for name, values in saved.arrays.items()},
                      [bool(table["possible"][r]) for r in rows], events, lowered, saved.own, saved.label)


def draw_pair_curves(ax, values: np.ndarray, labels: list[str], events: list[int], lowered: np.ndarray | None = None,
                     frame: int | None = None) -> None:
    """Each member's curve (values (M, T)) on one axis, labelled; the event frames as red dotted
    lines, the frames where the wall stands shaded grey (lighter while it moves), and `frame`
    as a cursor."""
    t = np.arange(values.shape[1])
    for t0 in t[lowered > 0] if lowered is not None else ():
        ax.axvspan(t0 - 0.5, t0 + 0.5, color="grey", alpha=0.25 if lowered[t0] >= 1 else 0.1, linewidth=0)
    if frame is not None:      # solid black: a cursor over the wall's grey shading stays seen
        ax.axvline(frame, color="black", linewidth=1.2, zorder=1)
    for event in sorted(set(e for e in events if e >= 0)):
        ax.axvline(event, color="red", linestyle=":", linewidth=1.5)
    for curve, label, style in zip(values, labels, ("-o", "--s", "-.^")):
        ax.plot(t, curve, style, markersize=3, label=label)


def member_labels(possible: list[bool]) -> list[str]:
    return [f"member {m} ({'possible' if p else 'impossible'})" for m, p in enumerate(possible)]


def _curves_figure(found: PairCurves, panels: list[tuple[str, str, np.ndarray]], title: str, marks: list[str],
                   frame: int | None) -> plt.Figure:
    """Panels (title, y label, values (2, T)) of one pair side by side, each on its own axis."""
    fig, axes = plt.subplots(1, len(panels), figsize=(3.7 * len(panels), 3.4), sharex=True, squeeze=False)
    frames = panels[0][2].shape[1]
    for ax, (name, unit, values) in zip(axes[0], panels):
        draw_pair_curves(ax, values, member_labels(found.possible), found.events, found.lowered, frame)
        first, second = values
        ax.set_title(f"{name}\nsum {_plain(first.sum())} vs {_plain(second.sum())}, "
                     f"max {_plain(first.max())} vs {_plain(second.max())}", fontsize=8)
        ax.set_xlabel("frame")
        if unit:
            ax.set_ylabel(unit)
    axes[0][0].set_xticks(np.arange(frames)[:: -(-frames // 8)])
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(title + (f"   ({'; '.join(marks)})" if marks else ""), fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return fig


def _plain(value: float) -> str:
    """A number in plain digits, three significant ones (no 1.06e+03): whole above 100."""
    digits = 0 if value == 0 else max(0, 2 - int(np.floor(np.log10(abs(value)))))
    return f"{value:.{digits}f}"


def _marks(data: str | Path | None, frame: int | None) -> list[str]:
    marks = ["red: event frame", "grey: the wall stands (lighter: it moves)"] if data is not None else []
    return marks + ([f"black line: frame {frame}"] if frame is not None else [])


def plot_surprise_curves(scores: str | Path, data: str | Path | None, scenario: str, setting: str, pair: int, *,
                         curves: str | Path | None = None, frame: int | None = None) -> plt.Figure:
    """Per-frame surprise of the two members of a test pair: s_img, s_dyn and their sum, and
    the excess (s_img - s_rec + s_dyn) when the curves hold s_rec (models with a perception);
    a model's own curve alone, on its own axis, for a model answering `surprise(videos)`.

    scores: a CSV written by `xvoe score`; curves: its per-frame curves (default:
    the .curves.npz beside it); data: the test split that was scored, for the event frame (red
    line) and the frames where the wall stands (grey; lighter while it moves), or None for
    the curves alone. frame: a frame to mark (a cursor)."""
    found = pair_curves(scores, data, scenario, setting, pair, curves, frame)
    if found.own:
        panels = [(found.own, f"surprise\n({found.label})", found.curves[found.own])]
    else:
        s_img, s_dyn = found.curves["s_img"], found.curves["s_dyn"]
        unit = f"surprise\n({MSE_LABEL})"
        # each term named in words too: the image and motion errors, the perception's own drawing error
        panels = [("s_img, image error", unit, s_img), ("s_dyn, motion error", "", s_dyn),
                  ("s_img + s_dyn, the score", "", s_img + s_dyn)]
        if "s_rec" in found.curves:
            panels.append(("excess: s_img - s_rec + s_dyn\n(s_rec: drawing error)", "",
                           excess(s_img, s_dyn, found.curves["s_rec"])))
    return _curves_figure(found, panels, f"{found.model}: {scenario} {setting} pair {pair}", _marks(data, frame),
                          frame)


def plot_surprise_definitions(scores: str | Path, data: str | Path | None, scenario: str, setting: str, pair: int,
                              *, curves: str | Path | None = None, frame: int | None = None) -> plt.Figure:
    """When each definition is surprised: the MSE's per-frame surprise (s_img + s_dyn) and the
    NLL's, -log p(x_t | x_<t), of the two members of a test pair side by side, each on its own
    axis, with the event frame marked. The scores need the NLL's curve (`xvoe score --surprise
    nll` or `both`); the arguments are `plot_surprise_curves`'."""
    found = pair_curves(scores, data, scenario, setting, pair, curves, frame)
    if "nll" not in found.curves:
        raise XvoeError(f"{scores} holds no NLL curve; score with --surprise nll or both (its SMC keeps one)")
    panels = [(name, unit, values) for name, (unit, values) in definition_curves(found.curves).items()]
    return _curves_figure(found, panels, f"{found.model}: {scenario} {setting} pair {pair}, two definitions",
                          _marks(data, frame), frame)


def definition_curves(curves: dict[str, np.ndarray], own: str | None = None,
                      label: str = MSE_LABEL) -> dict[str, tuple[str, np.ndarray]]:
    """Each surprise definition's per-frame curve in saved curves, by name: its axis label and
    values. With the NLL's: the MSE's (s_img + s_dyn) and the NLL's; without: the score's own (a
    model's `own` curve, under its `label`)."""
    if own:
        return {own: (label, curves[own])}
    summed = curves["s_img"] + curves["s_dyn"]
    if "nll" not in curves:
        return {"surprise": (MSE_LABEL, summed)}
    return {"MSE: s_img + s_dyn": (MSE_LABEL, summed),
            "NLL: -log p(x_t | x_<t)": ("nats", curves["nll"])}


def animate_pair(scores: str | Path, data: str | Path, scenario: str, setting: str, pair: int,
                 display_size: int = DISPLAY_SIZE) -> FuncAnimation:
    """A test pair frame by frame for a saved notebook or a slide: both members' scenes at
    `display_size` above their per-frame surprise (each definition the scores hold, as
    `plot_surprise_definitions`), a black line at the frame shown. Its `to_jshtml()` is a
    player that needs no kernel: the frames are drawn now, once."""
    check_display_size(display_size)
    found = pair_curves(scores, data, scenario, setting, pair)
    with store.open_dataset(data) as file:
        videos = find_pair(file, scenario, setting, pair)
        scenes = [display_video(file, index, display_size).rgbd[..., :3] for index in videos]
    curves = definition_curves(found.curves, found.own, found.label)
    labels = member_labels(found.possible)
    # drawn at its size: a player is not enlarged by the page, so its text is large enough here
    fig = plt.figure(figsize=(2.4 * max(2, len(curves)) + 0.8, 5.0), dpi=64)
    grid = fig.add_gridspec(2, 2 * len(curves), height_ratios=[1.2, 1])
    cursors, colours = [], []
    for column, (name, (unit, values)) in enumerate(curves.items()):
        ax = fig.add_subplot(grid[1, 2 * column:2 * column + 2] if len(curves) > 1 else grid[1, :])
        draw_pair_curves(ax, values, labels, found.events, found.lowered)
        colours = [line.get_color() for line in ax.get_lines()[-len(labels):]]
        cursors.append(ax.axvline(0, color="black", linewidth=1.2))
        ax.set_title(name, fontsize=11)
        ax.set_xlabel("frame", fontsize=10)
        ax.set_ylabel(unit, fontsize=10)
        ax.tick_params(labelsize=9)
    pictures = []
    for m, (scene, label) in enumerate(zip(scenes, labels)):
        ax = fig.add_subplot(grid[0, m * len(curves):(m + 1) * len(curves)])
        pictures.append(ax.imshow(scene[0], interpolation="nearest"))
        ax.set_title(label, fontsize=11, color=colours[m])       # the colour of its curve below
        ax.set_axis_off()
    caption = fig.suptitle("", fontsize=12)
    fig.text(0.5, 0.005, "red dotted: event frame; grey: the wall stands (lighter: it moves);\n"
             "black line: the frame shown", ha="center", va="bottom", fontsize=10)

    def draw(t: int) -> list:
        for picture, scene in zip(pictures, scenes):
            picture.set_data(scene[t])
        for cursor in cursors:
            cursor.set_xdata([t, t])
        caption.set_text(f"{scenario} {setting} pair {pair}, frame {t}" + (" (the event)" if t in found.events else ""))
        return [*pictures, *cursors, caption]

    fig.tight_layout(rect=(0, 0.08, 1, 1))
    animation = FuncAnimation(fig, draw, frames=len(scenes[0]), interval=300)
    plt.close(fig)       # drawn by its player, not again as a still below it
    return animation
