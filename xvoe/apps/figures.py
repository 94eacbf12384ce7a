"""Figures: contact sheets and animations of benchmark videos.

Everything here takes arrays or an open split file and returns a matplotlib Figure (or
writes a GIF), so notebooks, the command line and the tests draw the same pictures. Pictures of
videos draw the scene at a display size (`display_size`, 128 by default; None: the stored
frames alone) above what the model sees, its own frames enlarged without blur
(xvoe.scenes.display).
"""
from __future__ import annotations

import errno
from dataclasses import dataclass
from pathlib import Path

import h5py
import imageio_ffmpeg
import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.animation import FuncAnimation
from matplotlib.patches import Rectangle
from PIL import Image, ImageDraw

from ..errors import XvoeError
from ..evaluation.explain import DRAW_THRESHOLD, Explanation, drawn_pixels
from ..evaluation.metrics import excess, read_scores
from ..evaluation.score_curves import read_curves
from ..evaluation.score_headers import check_same_split, warn_unchecked
from ..evaluation.scorer import MSE_LABEL
from ..fingerprints import split_identity
from ..models.devices import device_of
from ..models.perception import normalise, to_uint8
from ..outputs import atomic_paths, claim_file, claim_scope, nearly_full
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE, check_display_size, display_video, enlarge, outline
from ..scenes.scenarios import SCENARIOS
from ..scenes.videos import _labels_of, _pair_rows, check_index, describe, find_pair, video_indices, wall_lowered
from ..training.data import perception_batch
from ..training.phydnet import load_phydnet

ID_COLORS = (np.array(plt.get_cmap("tab10").colors) * 255).astype(np.uint8)
ID_PALETTE = np.vstack([[[0, 0, 0]], ID_COLORS[:9]]).astype(np.uint8)   # 0 = background
# The outline of the model's hidden object: scene colours are drawn at random from all of RGB
# (xvoe.scenes.world.sample_colors), so each figure takes the one of these farthest from its scene's.
# Text of the sheets of frames, in points: readable at the notebooks' 72 dpi as at a saved PNG's 100,
# where a sheet 16 inches wide is shown shrunk to a page's width.
SHEET_FONT = 10
OUTLINE_COLORS = {"magenta": (255, 0, 255), "cyan": (0, 255, 255), "orange": (255, 128, 0), "blue": (0, 0, 255),
                  "red": (255, 0, 0), "yellow": (255, 255, 0), "green": (0, 160, 0), "purple": (128, 0, 255)}


def save_figure(figure: plt.Figure, out: str | Path, dpi: int = 100) -> Path:
    """Write a figure (its format from the suffix of `out`) whole or not at all, and close it,
    so that a loop of them holds no memory."""
    out = Path(out)
    try:
        with atomic_paths(out) as (tmp,):
            figure.savefig(tmp, format=out.suffix.lstrip(".").lower() or "png", dpi=dpi, bbox_inches="tight")
    finally:
        plt.close(figure)
    return out


def ids_to_rgb(ids: np.ndarray) -> np.ndarray:
    """Colour a slot-id map: black background, one fixed colour per slot."""
    return ID_PALETTE[np.minimum(ids, len(ID_PALETTE) - 1)]


def depth_to_rgb(depth: np.ndarray) -> np.ndarray:
    """Grey depth picture, near surfaces bright."""
    grey = 255 - depth
    return np.repeat(grey[..., None], 3, axis=-1)


def contact_sheet(rgbd: np.ndarray, ids: np.ndarray, titles: list[str],
                  event_frames: list[int] | None = None, display: np.ndarray | None = None) -> plt.Figure:
    """Frames in a row, RGB / depth / ids rows for each video, videos one above the other.

    rgbd: (M, T, H, W, 4), ids: (M, T, H, W). The event frame, where given, is outlined. With
    `display` (M, T, S, S, >= 3), the scene at a display size: a row of it above each video's
    rows, which are enlarged to its size.
    """
    videos, frames = rgbd.shape[:2]
    sheets = [sheet_rows(rgbd[m], ids[m], None if display is None else display[m]) for m in range(videos)]
    names = [name for name, _ in sheets[0]]
    rows = [row for sheet in sheets for _, row in sheet]
    per_video, height, width = len(names), rows[0].shape[1], rows[0].shape[2]
    gap = max(1, width // 16)
    title_gap = int(12 * gap * min(1.0, 64 / width))     # room for each video's title
    row_top = [m * title_gap + (per_video * m + k) * (height + gap) for m in range(videos) for k in range(per_video)]
    mosaic = np.full((videos * title_gap + len(rows) * (height + gap), frames * (width + gap), 3), 255, np.uint8)
    for r, row in enumerate(rows):
        for t in range(frames):
            y, x = row_top[r] + title_gap, t * (width + gap)
            mosaic[y:y + height, x:x + width] = row[t]
    scale = min(0.9 / 64, 1.1 / width)         # inches per pixel: a display frame about an inch wide
    fig, ax = plt.subplots(figsize=(max(4.0, mosaic.shape[1] * scale), mosaic.shape[0] * scale + 0.6 * videos))
    ax.imshow(mosaic, interpolation="nearest")
    ax.set_xticks([t * (width + gap) + width / 2 for t in range(frames)], [str(t) for t in range(frames)])
    ax.set_yticks([top + title_gap + height / 2 for top in row_top], names * videos)
    ax.tick_params(length=0, labelsize=SHEET_FONT)
    for spine in ax.spines.values():
        spine.set_visible(False)
    for m in range(videos):
        y0 = row_top[per_video * m] + title_gap
        ax.text(0, y0 - 2 * gap, titles[m], fontsize=SHEET_FONT + 1, va="bottom")
        event = (event_frames or [-1] * videos)[m]
        if event >= 0:
            ax.add_patch(Rectangle((event * (width + gap) - 0.5, y0 - 0.5), width,
                                   per_video * height + (per_video - 1) * gap,
                                   fill=False, edgecolor="red", linewidth=1.5))
    fig.tight_layout()
    return fig


def sheet_rows(rgbd: np.ndarray, ids: np.ndarray, display: np.ndarray | None = None) -> list[tuple[str, np.ndarray]]:
    """A video's named rows of (T, S, S, 3) pictures: the model's frames (RGB), their depth
    (near is bright) and slot ids (one colour per object); with `display`, the scene at that
    size first and the model's rows enlarged to it."""
    height, width = rgbd.shape[1:3]
    rows = [(f"model's {height}x{width}", rgbd[..., :3]), ("depth", depth_to_rgb(rgbd[..., 3])),
            ("ids", ids_to_rgb(ids))]
    if display is None:
        return rows
    size = display.shape[1]
    return [(f"scene {size}x{size}", display[..., :3]), *((name, enlarge(row, size)) for name, row in rows)]


def display_rows(file: h5py.File, indices: list[int], display_size: int | None) -> np.ndarray | None:
    """The scene of videos `indices` at `display_size` (M, T, S, S, 4), or None without one: where
    a video cannot be drawn anew at that size (a hand-made or imported split; `display_video`),
    its stored frames enlarged are the model's row already, not a scene to label as one."""
    if display_size is None:
        return None
    videos = [display_video(file, i, display_size) for i in indices]
    if not all(video.resimulated or display_size == file["rgbd"].shape[2] for video in videos):
        return None
    return np.stack([video.rgbd for video in videos])


def show_video(file: h5py.File, index: int, display_size: int | None = DISPLAY_SIZE) -> plt.Figure:
    """Contact sheet of video `index` (and its pair partner in a test file), the scene at
    `display_size` above the model's frames (None: the model's frames alone)."""
    indices = video_indices(file, index)
    rgbd = np.stack([store.read_frames(file, "rgbd", i) for i in indices])
    ids = np.stack([store.read_frames(file, "ids", i) for i in indices])
    events = [int(file["event_frame"][i]) for i in indices]
    titles = [describe(file, i) + (f", event frame {e}" if e >= 0 else "") for i, e in zip(indices, events)]
    return contact_sheet(rgbd, ids, titles, events, display_rows(file, indices, display_size))


def save_gif(file: h5py.File, index: int, out: str | Path, zoom: int = 3, frame_ms: int = 150,
             display_size: int | None = DISPLAY_SIZE) -> Path:
    """An animated GIF: the model's frames (RGB), depth and ids side by side, pair members one
    above the other; with `display_size`, the scene at that size first and the model's frames
    enlarged to it (else `zoom` times). Captioned: what each column is above them, and over each
    member what it is and the frame number (in red at the event frame)."""
    indices = video_indices(file, index)
    display = display_rows(file, indices, display_size)
    strips, names = [], []
    for m, i in enumerate(indices):
        rows = sheet_rows(store.read_frames(file, "rgbd", i), store.read_frames(file, "ids", i),
                          None if display is None else display[m])
        strips.append(np.concatenate([row for _, row in rows], axis=2))
        names = [name for name, _ in rows]
    if display is None:
        strips = [strip.repeat(zoom, axis=1).repeat(zoom, axis=2) for strip in strips]
    titles = [describe(file, i) for i in indices]
    events = [int(file["event_frame"][i]) if "event_frame" in file else -1 for i in indices]
    images = [_captioned(t, [strip[t] for strip in strips], names, titles, events) for t in range(len(strips[0]))]
    with atomic_paths(Path(out)) as (tmp,):
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=frame_ms, loop=0)
    return Path(out)


CAPTION = 14      # pixels of a caption line of PIL's default font


def _captioned(t: int, pictures: list[np.ndarray], columns: list[str], titles: list[str],
               events: list[int]) -> Image.Image:
    """Frame `t` of a GIF: a line naming the columns, then each member's picture (H, W, 3)
    under a line with its title and the frame number, red at its event frame."""
    width, column = pictures[0].shape[1], pictures[0].shape[1] // len(columns)
    canvas = np.full((CAPTION + sum(CAPTION + p.shape[0] for p in pictures), width, 3), 255, np.uint8)
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    for c, name in enumerate(columns):
        draw.text((c * column + 2, 1), name, fill=(0, 0, 0))
    top = CAPTION
    for picture, title, event in zip(pictures, titles, events):
        draw.text((2, top + 1), f"{title}, frame {t}" + (" (event)" if t == event else ""),
                  fill=(220, 0, 0) if t == event else (0, 0, 0))
        image.paste(Image.fromarray(picture), (0, top + CAPTION))
        top += CAPTION + picture.shape[0]
    return image


def save_video(file: h5py.File, index: int, out: str | Path, scores: str | Path | None = None,
               fps: int = 3, display_size: int | None = DISPLAY_SIZE) -> Path:
    """An MP4 for slides and a class: the video's pair side by side (each member the scene at
    `display_size` with the model's frame beside it), and, given the `scores` CSV of `xvoe
    score` (its curves beside it), each member's per-frame surprise under them with the frame
    marked as it plays: where the scores hold the NLL's curve, the MSE's and the NLL's side by
    side, each on its own axis, so that one sees when each definition is surprised."""
    indices = video_indices(file, index)
    videos = [store.read_frames(file, "rgbd", i)[..., :3] for i in indices]
    display = display_rows(file, indices, display_size)
    titles = [describe(file, i) for i in indices]
    curves = _video_curves(scores, file, indices) if scores is not None else None
    event = int(file["event_frame"][indices[-1]]) if "event_frame" in file else -1
    panels = [(video, display[m, ..., :3] if display is not None else None, title)
              for m, (video, title) in enumerate(zip(videos, titles))]
    if curves is not None:
        labels = _member_labels([bool(file["possible"][i]) for i in indices])
        lowered = np.max([wall_lowered(file, i) for i in indices], axis=0)
    pictures = []
    for t in range(videos[0].shape[0]):
        fig = plt.figure(figsize=(6.4, 4.8 if curves is not None else 3.2), dpi=100)
        grid = fig.add_gridspec(2 if curves is not None else 1, 2 * len(videos),
                                width_ratios=[3, 1] * len(videos) if display is not None else None)
        for column, (video, scene, title) in enumerate(panels):
            ax = fig.add_subplot(grid[0, 2 * column:2 * column + (1 if scene is not None else 2)])
            ax.imshow(video[t] if scene is None else scene[t], interpolation="nearest")
            ax.set_title(title.replace(" member", "\nmember"), fontsize=7, color="red" if t == event else "black")
            ax.set_axis_off()
            if scene is not None:
                beside = fig.add_subplot(grid[0, 2 * column + 1])
                beside.imshow(video[t], interpolation="nearest")
                beside.set_title(f"model's\n{video.shape[1]}x{video.shape[2]}", fontsize=6)
                beside.set_axis_off()
        if curves is not None:
            below = grid[1, :].subgridspec(1, len(curves), wspace=0.4)
            for column, (name, (unit, values)) in enumerate(curves.items()):
                ax = fig.add_subplot(below[0, column])
                draw_pair_curves(ax, values, labels, [event], lowered, frame=t)
                ax.set_title(name, fontsize=8)
                ax.set_xlabel("frame", fontsize=8)
                ax.set_ylabel(unit, fontsize=8)
                ax.tick_params(labelsize=7)
                if column == 0:
                    ax.legend(fontsize=6)
        fig.canvas.draw()
        pictures.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
        plt.close(fig)
    height, width = pictures[0].shape[:2]
    with atomic_paths(Path(out)) as (tmp,):
        try:
            # the container is named, not read off the temporary file's name; the encoder is quiet,
            # its failure is named here in one line
            writer = imageio_ffmpeg.write_frames(str(tmp), (width, height), fps=fps, codec="libx264",
                                                 pix_fmt_out="yuv420p", macro_block_size=1,
                                                 output_params=["-f", "mp4"], ffmpeg_log_level="quiet")
            writer.send(None)
            for picture in pictures:
                writer.send(np.ascontiguousarray(picture))
            writer.close()
        except (OSError, RuntimeError):     # the encoder ended early: its pipe broke
            if nearly_full(tmp.parent):
                raise OSError(errno.ENOSPC, "No space left on device", str(tmp)) from None
            raise XvoeError(f"the video encoder (ffmpeg) stopped before it wrote {out}") from None
    return Path(out)


def _video_curves(scores: str | Path, file: h5py.File, indices: list[int]) -> dict[str, tuple[str, np.ndarray]]:
    """Each definition's per-frame surprise (`definition_curves`) of videos `indices` of an open
    split from a scores CSV and its curves; scores of another split are refused."""
    check_same_split(scores, split_identity(file), file.filename)
    table = read_scores(scores)
    warn_unchecked(scores)
    curves = read_curves(Path(scores).with_suffix(".curves.npz"), len(table["index"]), scores)
    rows = {int(video): row for row, video in enumerate(table["index"])}
    missing = [i for i in indices if i not in rows]
    if missing:
        raise XvoeError(f"{scores} has no score of video {missing[0]}; were these scores made from this split?")
    picked = [rows[i] for i in indices]
    return definition_curves({name: values[picked] for name, values in curves.arrays.items()}, curves.own,
                             curves.label)


@claim_scope()
def show(path: str | Path, index: int, out: str | Path | None = None, overwrite: bool = False,
         scores: str | Path | None = None, display_size: int | None = DISPLAY_SIZE) -> Path | plt.Figure:
    """What `xvoe show` does: a PNG contact sheet, a GIF, or an MP4 (with `scores`, the
    surprise curves under the pair), chosen by the suffix of `out` (no `out`: the figure); the
    scene drawn at `display_size` beside the model's frames (None: those alone)."""
    if display_size is not None:
        check_display_size(display_size)
    suffix = Path(out).suffix.lower() if out is not None else None
    if suffix not in (None, ".png", ".gif", ".mp4"):
        raise XvoeError(f"--out must end in .png, .gif or .mp4, not {suffix or 'nothing'}")
    if scores is not None and suffix != ".mp4":
        raise XvoeError("--scores draws surprise curves into an MP4; give --out NAME.mp4")
    with store.open_dataset(path) as file:
        check_index(file, index)
        if out is not None:
            claim_file(out, overwrite)
        if suffix == ".gif":
            return save_gif(file, index, out, display_size=display_size)
        if suffix == ".mp4":
            return save_video(file, index, out, scores, display_size=display_size)
        fig = show_video(file, index, display_size)
    return fig if out is None else save_figure(fig, out)


def reconstruction_sheet(frames: np.ndarray, composite: np.ndarray, inputs: np.ndarray, decoded: np.ndarray,
                         slot_names: list[list[str]]) -> plt.Figure:
    """Originals against reconstructions, one frame per row: the frame and its composite (RGB and
    depth), then each component's input (masked frame) beside its decoding.

    frames, composite: (F,H,W,4) uint8; inputs, decoded: (F,C,H,W,4) uint8 for the C components
    shown in each row, named by slot_names[f] (rows with fewer components leave cells empty).
    """
    rows, columns = len(frames), 4 + 2 * inputs.shape[1]
    fig, axes = plt.subplots(rows, columns, figsize=(0.85 * columns, 0.95 * rows + 0.3), squeeze=False)
    for r in range(rows):
        cells = [(frames[r, ..., :3], "frame"), (composite[r, ..., :3], "composite"),
                 (depth_to_rgb(frames[r, ..., 3]), "depth"), (depth_to_rgb(composite[r, ..., 3]), "comp. depth")]
        for c, name in enumerate(slot_names[r]):
            cells += [(inputs[r, c, ..., :3], f"{name} in"), (decoded[r, c, ..., :3], f"{name} out")]
        for c, ax in enumerate(axes[r]):
            ax.set_axis_off()
            if c < len(cells):
                ax.imshow(cells[c][0], interpolation="nearest")
                ax.set_title(cells[c][1], fontsize=6, pad=2)
    fig.tight_layout(pad=0.2)
    return fig


def save_reconstructions(model, rgbd: np.ndarray, ids: np.ndarray, out: str | Path, rows: int = 4,
                         seed: int = 0) -> Path:
    """Draw `reconstruction_sheet` for a few frames of (V,T,H,W,4) videos with the most objects."""

    size, slots = rgbd.shape[2], max(1, int(ids.max(initial=0)))
    flat_rgbd, flat_ids = rgbd.reshape(-1, size, size, 4), ids.reshape(-1, size, size)
    objects = np.array([len(np.unique(m)) - 1 for m in flat_ids])
    most = np.flatnonzero(objects == objects.max())
    rng = np.random.default_rng(seed)
    chosen = np.sort(rng.choice(most, rows, replace=False) if len(most) >= rows
                     else np.argsort(-objects, kind="stable")[:rows])
    noise = np.zeros((len(chosen), slots + 1, model.config.latent_dim), np.float32)
    batch = perception_batch(flat_rgbd[chosen], flat_ids[chosen], slots, noise, noise[:1, 0]).to(device_of(model))
    with torch.no_grad():
        result = model.forward_batch(batch, sample=False)
    shown = int(objects[chosen].max()) + 1
    inputs = np.full((len(chosen), shown, size, size, 4), 255, np.uint8)
    outputs = inputs.copy()
    names = [["bg"] for _ in chosen]
    inputs[:, 0], outputs[:, 0] = to_uint8(batch.background).numpy(), to_uint8(result["background"]).numpy()
    for i, (f, k) in enumerate(zip(batch.object_frame.tolist(), batch.object_slot.tolist())):
        c = len(names[f])
        inputs[f, c], outputs[f, c] = to_uint8(batch.objects[i]).numpy(), to_uint8(result["objects"][i]).numpy()
        names[f].append(f"slot {k}")
    fig = reconstruction_sheet(flat_rgbd[chosen], to_uint8(result["composite"]).numpy(), inputs, outputs, names)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return Path(out)


# --- the paper's metric figures -----------------------------------------------------------

def _select(rows: list[dict], metric: str, column: str) -> list[dict]:
    return [r for r in rows if r["metric"] == metric and r["column"] == column]


def _models(rows: list[dict]) -> list[str]:
    return list(dict.fromkeys(r["model"] for r in rows))


# One colour per score column in every chart, so that a colour means one quantity throughout:
# a series named after a column ("nll", or "nll (NLL)") takes its colour, any other the next
# colour no column holds.
COLUMN_COLORS = {"score": "tab:blue", "paper_score": "tab:orange", "excess": "tab:red", "nll": "tab:purple",
                 "nll_excess": "tab:brown", "s_img": "tab:olive", "s_dyn": "tab:cyan"}
_FREE_COLORS = ("tab:green", "tab:gray", "gold", "navy", "lime", "teal")
IDEAL_COLOR = "magenta"     # the ideal's dashed line: no bar, cap or interval is drawn in it


def _series_colors(names: list[str]) -> list[str]:
    """The colour of each series: its column's (COLUMN_COLORS), else the next free one."""
    free = iter(_FREE_COLORS * (1 + len(names) // len(_FREE_COLORS)))
    return [COLUMN_COLORS.get(name.split(" (")[0]) or next(free) for name in names]


def _bars(ax, groups: list[str], models: list[str], lookup, width: float = 0.8) -> None:
    """Grouped bars with 95% intervals: lookup(model, group) -> row or None. Each bar's value is
    also marked by a dash in its colour, so that a bar of height 0 is seen; each group's tick
    says how many units (pairs, or videos) its bars rest on."""
    step = width / max(1, len(models))
    counts: dict[int, set[int]] = {}
    for m, (model, colour) in enumerate(zip(models, _series_colors(models))):
        xs, values, errors = [], [], [[], []]
        for g, group in enumerate(groups):
            row = lookup(model, group)
            if row is None:
                continue
            xs.append(g - width / 2 + step * (m + 0.5))
            values.append(100 * row["value"])
            # a percentile interval of a statistic full of ties may stop short of the value itself
            errors[0].append(max(0.0, 100 * (row["value"] - row["low"])))
            errors[1].append(max(0.0, 100 * (row["high"] - row["value"])))
            if row.get("count"):
                counts.setdefault(g, set()).add(int(row["count"]))
        ax.bar(xs, values, step * 0.95, yerr=errors, capsize=2, label=model, color=colour)
        ax.scatter(xs, values, marker="_", s=(72 * step * 0.9) ** 2 / 4, linewidths=2, zorder=3, color=colour)
    ax.set_xticks(range(len(groups)), [f"{group}\n(n={'/'.join(map(str, sorted(counts[g])))})" if g in counts
                                       else group for g, group in enumerate(groups)])


def _ideal_lines(ax, ideals: list[float], width: float = 0.8) -> None:
    """Each group's ideal (a share) as a dashed line across the whole group, in a colour no bar
    or interval has: short black dashes would read as the intervals' caps."""
    groups = np.arange(len(ideals))
    ax.hlines(100 * np.asarray(ideals), groups - width / 2 - 0.05, groups + width / 2 + 0.05, colors=IDEAL_COLOR,
              linestyles="--", linewidth=1.8, zorder=4, label="ideal")


def _title_column(column: str) -> str:
    """The column in a chart's title: none for `score`, which a legend of variants renames."""
    return "" if column == "score" else f" ({column})"


HOLISTIC_N = "n: pair indices, each pooling the scenario's settings (S1-S3)"


def _legend_outside(ax, **kwargs) -> None:
    """The legend right of the axes, where no bar or interval can be under it."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1), borderaxespad=0, **kwargs)


def plot_holistic(rows: list[dict], column: str = "score") -> plt.Figure:
    """Fig. 5a: holistic accuracy (AUC) per scenario, models side by side, ideal and chance."""
    chosen = _select(rows, "holistic", column)
    scenarios = list(dict.fromkeys(r["scenario"] for r in chosen))
    index = {(r["model"], r["scenario"]): r for r in chosen}
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(scenarios), 3.2))
    _bars(ax, scenarios, _models(chosen), lambda m, s: index.get((m, s)))
    ax.axhline(100, color=IDEAL_COLOR, linestyle="--", linewidth=1.8, label="ideal")
    ax.axhline(50, color="grey", linestyle=":", linewidth=1, label="chance")
    ax.set_ylim(-4, 105)      # below 0: a bar at 0 shows its dash
    ax.set_ylabel("holistic accuracy (%)")
    ax.set_title(f"Holistic metric{_title_column(column)}, 95% intervals;\n{HOLISTIC_N}", fontsize=9)
    _legend_outside(ax)
    fig.tight_layout()
    return fig


def plot_comparative(rows: list[dict], column: str = "score") -> plt.Figure:
    """Fig. 6: comparative accuracy per setting against the ideal (100/50/100), and the
    difference from the ideal below."""
    chosen = _select(rows, "comparative", column)
    settings = list(dict.fromkeys(f"{r['scenario']} {r['setting']}" for r in chosen))
    index = {(r["model"], f"{r['scenario']} {r['setting']}"): r for r in chosen}
    ideal = {f"{r['scenario']} {r['setting']}": r["ideal"] for r in chosen}
    models = _models(chosen)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(1.5 + 0.75 * len(settings), 5.2), sharex=True,
                                      gridspec_kw={"height_ratios": [2, 1]})
    _bars(top, settings, models, lambda m, s: index.get((m, s)))
    _ideal_lines(top, [ideal[s] for s in settings])
    top.set_ylim(-4, 105)
    top.set_ylabel("comparative accuracy (%)")
    top.set_title(f"Comparative metric{_title_column(column)}, 95% Wilson intervals; n: pairs", fontsize=9)
    _legend_outside(top)

    def difference(model, setting):
        row = index.get((model, setting))
        if row is None:
            return None
        return {**row, "value": row["value"] - row["ideal"], "low": row["low"] - row["ideal"],
                "high": row["high"] - row["ideal"]}

    _bars(bottom, settings, models, difference)
    bottom.axhline(0, color="black", linewidth=1)
    bottom.set_ylabel("minus ideal (points)")
    bottom.tick_params(axis="x", labelrotation=45, labelsize=8)
    fig.tight_layout()
    return fig


def plot_components(rows: list[dict], model: str, metric: str = "comparative") -> plt.Figure:
    """Fig. 5c: the metric of the whole score against s_img alone and s_dyn alone."""
    chosen = [r for r in rows if r["model"] == model and r["metric"] == metric]
    key = (lambda r: r["scenario"]) if metric == "holistic" else (lambda r: f"{r['scenario']} {r['setting']}")
    groups = list(dict.fromkeys(key(r) for r in chosen))
    index = {(r["column"], key(r)): r for r in chosen}
    columns = list(dict.fromkeys(r["column"] for r in chosen))
    fig, ax = plt.subplots(figsize=(1.5 + 0.75 * len(groups), 3.2))
    _bars(ax, groups, columns, lambda c, g: index.get((c, g)))
    ideals = {key(r): r["ideal"] for r in chosen}
    _ideal_lines(ax, [ideals[g] for g in groups])
    ax.set_ylim(-4, 105)
    ax.set_ylabel(f"{metric} accuracy (%)")
    n = HOLISTIC_N if metric == "holistic" else "n: pairs"
    ax.set_title(f"Score components: {model}, 95% intervals; {n}", fontsize=9)
    ax.tick_params(axis="x", labelrotation=45, labelsize=8)
    _legend_outside(ax)
    fig.tight_layout()
    return fig


# --- rows of frames: explanations, disagreeing pairs ---------------------------------------

def draw_frame_rows(ax, videos: list[np.ndarray], labels: list[str], title: str,
                    numbers: list[int] | None = None, marked: int = -1) -> None:
    """Videos (T, H, W, >=3) uint8 as rows of frames on one axis, each row labelled; the
    frames numbered by `numbers` (default 0, 1, ...), the column of frame number `marked`
    outlined in red."""
    frames, height, width = videos[0].shape[:3]
    numbers = list(range(frames)) if numbers is None else numbers
    gap = max(1, width // 16)
    mosaic = np.full((len(videos) * (height + gap), frames * (width + gap), 3), 255, np.uint8)
    for r, video in enumerate(videos):
        for t in range(frames):
            y, x = r * (height + gap), t * (width + gap)
            mosaic[y:y + height, x:x + width] = video[t, ..., :3]
    ax.imshow(mosaic, interpolation="nearest")
    ax.set_xticks([t * (width + gap) + width / 2 for t in range(frames)], [str(n) for n in numbers])
    ax.set_yticks([r * (height + gap) + height / 2 for r in range(len(videos))], labels)
    ax.tick_params(length=0, labelsize=SHEET_FONT)
    for spine in ax.spines.values():
        spine.set_visible(False)
    if marked in numbers:
        ax.add_patch(Rectangle((numbers.index(marked) * (width + gap) - 0.5, -0.5), width,
                               len(videos) * (height + gap) - gap, fill=False, edgecolor="red", linewidth=1.5))
    ax.set_title(title, fontsize=SHEET_FONT + 1)


def plot_onset(pairs: dict[str, list[dict]]) -> plt.Figure:
    """Violation onset: for each scenario, how many S1/S3 pairs' surprise difference peaks how
    many frames after the event (0: at the event frame; negative: before it), one series per
    model (`xvoe.evaluation.metrics.onset_pairs`)."""
    scenarios = list(dict.fromkeys(p["scenario"] for found in pairs.values() for p in found))
    if not scenarios:
        raise XvoeError("no S1 or S3 pair with an event frame to time")
    offsets = [p["peak_offset"] for found in pairs.values() for p in found]
    edges = np.arange(min(offsets) - 0.5, max(offsets) + 1.5)
    fig, axes = plt.subplots(1, len(scenarios), figsize=(3.2 * len(scenarios), 2.8), sharey=True, squeeze=False)
    for ax, scenario in zip(axes[0], scenarios):
        for model, found in pairs.items():
            ax.hist([p["peak_offset"] for p in found if p["scenario"] == scenario], bins=edges, alpha=0.6,
                    label=model)
        ax.axvline(0, color="red", linewidth=1)
        ax.set_title(scenario, fontsize=9)
        ax.set_xlabel("frames from event to peak", fontsize=8)
    axes[0][0].set_ylabel("S1/S3 pairs", fontsize=8)
    _legend_outside(axes[0][-1])
    fig.tight_layout()
    return fig


def plot_explanation(explanation: Explanation) -> plt.Figure:
    """The paper's Fig. 7/8: observed frames, the scene behind the wall as the model believes
    it (occluder left out), and the explanation object alone; the rows an explanation gives
    (`Explanation.figure_rows`: the NLL's draws each hypothesis only where its probability
    exceeds DRAW_THRESHOLD), so the MSE and the NLL explanations draw alike, and its notes as
    text under them. With the scene at a display size (`xvoe.apps.verbs.with_display`), it comes
    first with the explanation drawn onto it (`explanation_overlay`), and the model's rows are
    enlarged to its size (where the scene is the model's frames enlarged, it stands for the
    observed row). The figure's `drawn_rows` lists the (kind, label) of each row drawn."""
    rows = explanation.figure_rows()
    if explanation.display is not None:
        size = explanation.display.shape[1]
        scene, colour = explanation_overlay(explanation)
        # a display that is the model's frames enlarged is the observed row already, outlined
        shown = [row for row in rows if explanation.display_resimulated or row[0] != "observed"]
        rows = [("scene", _scene_label(explanation, size, colour), scene),
                *((kind, name, enlarge(video, size)) for kind, name, video in shown)]
    frames = explanation.observed.shape[0]
    title_lines = explanation.title.count("\n") + 1
    notes = explanation.notes()
    cell = _cell_inches(rows[0][2].shape[1])
    fig, ax = plt.subplots(figsize=(max(4.0, frames * cell), len(rows) * cell + 0.3 + 0.25 * title_lines
                                    + 0.25 * len(notes)))
    draw_frame_rows(ax, [video for _, _, video in rows], [name for _, name, _ in rows], explanation.title)
    if notes:
        ax.set_xlabel("\n".join(notes), fontsize=SHEET_FONT, labelpad=6)
    fig.tight_layout()
    fig.drawn_rows = [(kind, name) for kind, name, _ in rows]     # what was drawn, for a reader to check
    return fig


def _scene_label(explanation: Explanation, size: int, colour: str | None) -> str:
    """The scene row's label: what its lines are, only those drawn."""
    height, width = explanation.observed.shape[1:3]
    lines = [f"scene {size}x{size}" if explanation.display_resimulated else f"model's {height}x{width},\nenlarged"]
    if colour is not None:
        p = explanation.p_drawn
        lines.append(f"{colour}: the model's\nhidden object" + (f" (p = {p:.2f})" if p < 1.0 else ""))
    if explanation.true_hidden is not None and explanation.true_hidden.any():
        lines.append("dashed: the true one")
    return ":\n".join([lines[0], "\n".join(lines[1:])]) if len(lines) > 1 else lines[0]


def _cell_inches(size: int) -> float:
    """Inches a frame of `size` pixels takes in a figure of frame rows: a display frame near
    its own size at the figures' dpi, the model's small frames as before."""
    return max(0.8, min(1.1, size / 100))


def explanation_overlay(explanation: Explanation) -> tuple[np.ndarray, str | None]:
    """The scene at its display size (T, S, S, 3) with the model's explanation drawn onto it,
    and the name of the outline's colour (None: no hidden object drawn). The decoded hidden
    object, enlarged (bilinear), is blended in where it stands and outlined inside its edge in
    the colour of OUTLINE_COLORS farthest from the scene's, both at an opacity of its
    probability (`Explanation.p_drawn`; nothing below DRAW_THRESHOLD); the true never-seen
    objects are outlined a pixel outside theirs, thin, dashed black and white, so that the two lines stay
    apart where they agree; both are seen through the wall, as the model sees the object."""
    scene = explanation.display[..., :3].copy()
    size = scene.shape[1]
    p, name = explanation.p_drawn, None
    if p > DRAW_THRESHOLD:
        depth = _resized(explanation.hidden_object[..., 3], size)
        colour = np.stack([_resized(explanation.hidden_object[..., c], size) for c in range(3)], axis=-1)
        drawn = drawn_pixels(np.concatenate([colour, depth[..., None]], axis=-1))
        name, line = outline_color(scene)
        blended = scene.astype(np.float32)
        blended[drawn] += 0.5 * p * (colour[drawn].astype(np.float32) - blended[drawn])
        edge = outline(drawn)
        blended[edge] += p * (np.asarray(line, np.float32) - blended[edge])
        scene = np.round(blended).astype(np.uint8)
    if explanation.true_hidden is not None:
        # a thin ring one pixel out from it: the model's outline, inside its own edge, stays seen
        edge = outline(~explanation.true_hidden, 2) & ~outline(~explanation.true_hidden, 1)
        rows, columns = np.indices((size, size))
        light = ((rows + columns) // 4) % 2 == 0                  # dashes of four pixels
        scene[edge & light] = 255
        scene[edge & ~light] = 0
    return scene, name


def outline_color(scene: np.ndarray) -> tuple[str, tuple[int, int, int]]:
    """The name and RGB of the colour of OUTLINE_COLORS farthest (L1) from every colour of
    `scene` (..., 3) uint8."""
    colours = np.unique(scene.reshape(-1, 3), axis=0).astype(np.int32)
    distance = {name: int(np.abs(colours - np.array(rgb)).sum(axis=1).min()) for name, rgb in OUTLINE_COLORS.items()}
    name = max(OUTLINE_COLORS, key=lambda n: distance[n])      # ties: the first listed
    return name, OUTLINE_COLORS[name]


def _resized(channel: np.ndarray, size: int) -> np.ndarray:
    """One uint8 channel of frames (T, H, W) resized to (T, size, size), bilinear."""
    return np.stack([np.asarray(Image.fromarray(frame).resize((size, size), Image.BILINEAR)) for frame in channel])


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
    cell = _cell_inches(display_size or file["rgbd"].shape[2])
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
    cell = _cell_inches(display_size)
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


# --- surprise over frames, and frames side by side ----------------------------------------

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
    rows = _pair_rows(table["scenario"], table["setting"], table["pair"], table["member"], scenario, setting, pair,
                      str(scores))
    videos = [int(table["index"][r]) for r in rows]
    frames = saved.total.shape[1]
    events, lowered = [-1, -1], np.zeros(frames)
    if data is not None:
        with store.open_dataset(data) as file:
            check_same_split(scores, split_identity(file), data)
            warn_unchecked(scores)
            for video in videos:
                if not 0 <= video < file["rgbd"].shape[0] or _labels_of(file, video) != (scenario, setting, pair):
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


def _member_labels(possible: list[bool]) -> list[str]:
    return [f"member {m} ({'possible' if p else 'impossible'})" for m, p in enumerate(possible)]


def _curves_figure(found: PairCurves, panels: list[tuple[str, str, np.ndarray]], title: str, marks: list[str],
                   frame: int | None) -> plt.Figure:
    """Panels (title, y label, values (2, T)) of one pair side by side, each on its own axis."""
    fig, axes = plt.subplots(1, len(panels), figsize=(3.7 * len(panels), 3.4), sharex=True, squeeze=False)
    frames = panels[0][2].shape[1]
    for ax, (name, unit, values) in zip(axes[0], panels):
        draw_pair_curves(ax, values, _member_labels(found.possible), found.events, found.lowered, frame)
        first, second = values
        ax.set_title(f"{name}\nsum {first.sum():.3g} vs {second.sum():.3g}, "
                     f"max {first.max():.3g} vs {second.max():.3g}", fontsize=8)
        ax.set_xlabel("frame")
        if unit:
            ax.set_ylabel(unit)
    axes[0][0].set_xticks(np.arange(frames)[:: -(-frames // 8)])
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, frameon=False)
    fig.suptitle(title + (f"   ({'; '.join(marks)})" if marks else ""), fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return fig


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
    labels = _member_labels(found.possible)
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


def frame_rows(rows: list[tuple[str, np.ndarray]], title: str = "") -> plt.Figure:
    """Named rows of frames side by side, each (T, H, W, C) with C >= 3 (RGB first), all of one
    size: `Explanation.rows()` plus rows of one's own (e.g. `true_objects`) make a comparison."""
    if not rows:
        raise XvoeError("frame_rows needs at least one row")
    shapes = {tuple(video.shape[:3]) for _, video in rows}
    if len(shapes) != 1:
        raise XvoeError(f"rows differ in shape: {sorted(shapes)}")
    frames = shapes.pop()[0]
    lines = title.count("\n") + 1 if title else 0
    fig, ax = plt.subplots(figsize=(max(4.0, frames * 0.8), len(rows) * 0.8 + 0.4 + 0.25 * lines))
    draw_frame_rows(ax, [video for _, video in rows], [name for name, _ in rows], title)
    fig.tight_layout()
    return fig


# --- a pixel predictor's view: PhyDNet's one-step predictions -----------------------------

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
