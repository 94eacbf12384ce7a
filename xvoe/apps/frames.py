"""Pictures of a split's videos: contact sheets, rows of frames, animated GIFs, and sheets of
a perception module's reconstructions.

Everything here takes arrays or an open split file and returns a matplotlib Figure (or writes a
file), so notebooks, the command line and the tests draw the same pictures. Pictures of videos
draw the scene at a display size (`display_size`, 128 by default; None: the stored frames
alone) above what the model sees, its own frames enlarged without blur (xvoe.scenes.display).
"""
from __future__ import annotations

from pathlib import Path

import h5py
import matplotlib.pyplot as plt
import numpy as np
import torch
from matplotlib.collections import PatchCollection
from matplotlib.patches import Rectangle
from PIL import Image, ImageDraw

from ..errors import XvoeError
from ..models.devices import device_of
from ..models.perception import to_uint8
from ..outputs import atomic_paths
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE, display_video, enlarge
from ..scenes.videos import describe, video_indices
from ..training.data import perception_batch

__all__ = ["ID_COLORS", "ID_PALETTE", "SHEET_FONT", "save_figure", "ids_to_rgb", "depth_to_rgb", "contact_sheet",
           "sheet_rows", "display_rows", "show_video", "save_gif", "CAPTION", "cell_inches", "draw_frame_rows",
           "frame_rows", "reconstruction_sheet", "save_reconstructions"]


ID_COLORS = (np.array(plt.get_cmap("tab10").colors) * 255).astype(np.uint8)
ID_PALETTE = np.vstack([[[0, 0, 0]], ID_COLORS[:9]]).astype(np.uint8)   # 0 = background
# Text of the sheets of frames, in points: readable at the notebooks' 72 dpi as at a saved PNG's 100,
# where a sheet 16 inches wide is shown shrunk to a page's width.
SHEET_FONT = 10


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
    scale = 1.1 / width         # inches per pixel: a frame about an inch wide, the model's small ones too
    title_gap = round(0.4 / scale)      # room for each video's title
    row_top = [m * title_gap + (per_video * m + k) * (height + gap) for m in range(videos) for k in range(per_video)]
    mosaic = np.full((videos * title_gap + len(rows) * (height + gap), frames * (width + gap), 3), 255, np.uint8)
    for r, row in enumerate(rows):
        for t in range(frames):
            y, x = row_top[r] + title_gap, t * (width + gap)
            mosaic[y:y + height, x:x + width] = row[t]
    fig, ax = plt.subplots(figsize=(max(4.0, mosaic.shape[1] * scale), mosaic.shape[0] * scale + 0.6 * videos))
    ax.imshow(mosaic, interpolation="nearest")
    ax.set_xticks([t * (width + gap) + width / 2 for t in range(frames)], [str(t) for t in range(frames)])
    ax.set_yticks([top + title_gap + height / 2 for top in row_top], names * videos)
    ax.tick_params(length=0, labelsize=SHEET_FONT)
    for spine in ax.spines.values():
        spine.set_visible(False)
    _frame_edges(ax, [top + title_gap for top in row_top], frames, height, width, gap)
    for m in range(videos):
        y0 = row_top[per_video * m] + title_gap
        ax.text(0, y0 - 2 * gap, titles[m], fontsize=SHEET_FONT + 1, va="bottom")
        event = (event_frames or [-1] * videos)[m]
        if event >= 0:
            ax.add_patch(Rectangle((event * (width + gap) - 0.5, y0 - 0.5), width,
                                   per_video * height + (per_video - 1) * gap,
                                   fill=False, edgecolor="red", linewidth=1.5, zorder=3))
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


def cell_inches(size: int) -> float:
    """Inches a frame of `size` pixels takes in a figure of frame rows: a display frame near
    its own size at the figures' dpi, the model's small frames as before."""
    return max(0.8, min(1.1, size / 100))


def _frame_edges(ax, tops: list[int], frames: int, height: int, width: int, gap: int) -> None:
    """A thin grey edge around every frame of a mosaic (rows starting at pixel rows `tops`):
    a white frame (an object alone on white) is otherwise lost on the white page."""
    edges = [Rectangle((t * (width + gap) - 0.5, top - 0.5), width, height) for top in tops for t in range(frames)]
    ax.add_collection(PatchCollection(edges, facecolor="none", edgecolor="0.6", linewidth=0.5, zorder=2))


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
    _frame_edges(ax, [r * (height + gap) for r in range(len(videos))], frames, height, width, gap)
    if marked in numbers:
        ax.add_patch(Rectangle((numbers.index(marked) * (width + gap) - 0.5, -0.5), width,
                               len(videos) * (height + gap) - gap, fill=False, edgecolor="red", linewidth=1.5,
                               zorder=3))
    ax.set_title(title, fontsize=SHEET_FONT + 1)


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
