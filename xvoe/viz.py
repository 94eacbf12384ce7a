"""Figures: contact sheets and animations of benchmark videos.

Everything here takes arrays or an open split file and returns a matplotlib Figure (or
writes a GIF), so notebooks, the command line and the tests draw the same pictures.
"""
from __future__ import annotations

from pathlib import Path

import h5py
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Rectangle

from . import store
from .errors import XvoeError

ID_COLORS = (np.array(plt.get_cmap("tab10").colors) * 255).astype(np.uint8)
ID_PALETTE = np.vstack([[[0, 0, 0]], ID_COLORS[:9]]).astype(np.uint8)   # 0 = background


def ids_to_rgb(ids: np.ndarray) -> np.ndarray:
    """Colour a slot-id map: black background, one fixed colour per slot."""
    return ID_PALETTE[np.minimum(ids, len(ID_PALETTE) - 1)]


def depth_to_rgb(depth: np.ndarray) -> np.ndarray:
    """Grey depth picture, near surfaces bright."""
    grey = 255 - depth
    return np.repeat(grey[..., None], 3, axis=-1)


def video_indices(file: h5py.File, index: int) -> list[int]:
    """The videos to show for `index`: its whole pair in a test file, itself otherwise."""
    count = file["rgbd"].shape[0]
    if not 0 <= index < count:
        raise XvoeError(f"index {index} is out of range: the file holds videos 0..{count - 1}")
    if file.attrs["split"] == "test":
        first = index - int(file["member"][index])
        return [first, first + 1]
    return [index]


def describe(file: h5py.File, index: int) -> str:
    if file.attrs["split"] == "test":
        label = "possible" if file["possible"][index] else "impossible"
        return (f"{file['scenario'].asstr()[index]} {file['setting'].asstr()[index]} "
                f"pair {file['pair'][index]} member {file['member'][index]} ({label})")
    has_wall = "with wall" if file["has_wall"][index] else "no wall"
    return f"train video {index}: {file['group'].asstr()[index]}, {has_wall}"


def contact_sheet(rgbd: np.ndarray, ids: np.ndarray, titles: list[str],
                  event_frames: list[int] | None = None) -> plt.Figure:
    """Frames in a row, RGB / depth / ids rows for each video, videos one above the other.

    rgbd: (M, T, H, W, 4), ids: (M, T, H, W). The event frame, where given, is outlined.
    """
    videos, frames, height, width, _ = rgbd.shape
    rows = []
    for m in range(videos):
        rows += [rgbd[m, ..., :3], depth_to_rgb(rgbd[m, ..., 3]), ids_to_rgb(ids[m])]
    gap = max(1, width // 16)
    title_gap = 12 * gap                       # room for each video's title
    row_top = [m * title_gap + (3 * m + k) * (height + gap) for m in range(videos) for k in range(3)]
    mosaic = np.full((videos * title_gap + len(rows) * (height + gap), frames * (width + gap), 3), 255, np.uint8)
    for r, row in enumerate(rows):
        for t in range(frames):
            y, x = row_top[r] + title_gap, t * (width + gap)
            mosaic[y:y + height, x:x + width] = row[t]
    scale = 0.9 / 64
    fig, ax = plt.subplots(figsize=(max(4.0, mosaic.shape[1] * scale), mosaic.shape[0] * scale + 0.5 * videos))
    ax.imshow(mosaic, interpolation="nearest")
    ax.set_xticks([t * (width + gap) + width / 2 for t in range(frames)], [str(t) for t in range(frames)])
    ax.set_yticks([top + title_gap + height / 2 for top in row_top],
                  ["RGB", "depth", "ids"] * videos)
    ax.tick_params(length=0, labelsize=7)
    for spine in ax.spines.values():
        spine.set_visible(False)
    for m in range(videos):
        y0 = row_top[3 * m] + title_gap
        ax.text(0, y0 - 2 * gap, titles[m], fontsize=8, va="bottom")
        event = (event_frames or [-1] * videos)[m]
        if event >= 0:
            ax.add_patch(Rectangle((event * (width + gap) - 0.5, y0 - 0.5), width, 3 * height + 2 * gap,
                                   fill=False, edgecolor="red", linewidth=1.5))
    fig.tight_layout()
    return fig


def show_video(file: h5py.File, index: int) -> plt.Figure:
    """Contact sheet of video `index` (and its pair partner in a test file)."""
    indices = video_indices(file, index)
    rgbd = np.stack([file["rgbd"][i] for i in indices])
    ids = np.stack([file["ids"][i] for i in indices])
    events = [int(file["event_frame"][i]) for i in indices]
    titles = [describe(file, i) + (f", event frame {e}" if e >= 0 else "") for i, e in zip(indices, events)]
    return contact_sheet(rgbd, ids, titles, events)


def save_gif(file: h5py.File, index: int, out: str | Path, zoom: int = 3, frame_ms: int = 150) -> Path:
    """An animated GIF: RGB, depth and ids side by side, pair members one above the other."""
    from PIL import Image

    indices = video_indices(file, index)
    strips = []
    for i in indices:
        rgbd, ids = file["rgbd"][i], file["ids"][i]
        strips.append(np.concatenate([rgbd[..., :3], depth_to_rgb(rgbd[..., 3]), ids_to_rgb(ids)], axis=2))
    movie = np.concatenate(strips, axis=1)
    movie = movie.repeat(zoom, axis=1).repeat(zoom, axis=2)
    images = [Image.fromarray(frame) for frame in movie]
    images[0].save(out, save_all=True, append_images=images[1:], duration=frame_ms, loop=0)
    return Path(out)


def show(path: str | Path, index: int, out: str | Path | None = None) -> Path | plt.Figure:
    """What `xvoe show` does: a PNG contact sheet or a GIF, chosen by the suffix of `out`."""
    suffix = Path(out).suffix.lower() if out is not None else None
    if suffix not in (None, ".png", ".gif"):
        raise XvoeError(f"--out must end in .png or .gif, not {suffix or 'nothing'}")
    with store.open_dataset(path) as file:
        if suffix == ".gif":
            return save_gif(file, index, out)
        fig = show_video(file, index)
    if out is None:
        return fig
    fig.savefig(out, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return Path(out)
