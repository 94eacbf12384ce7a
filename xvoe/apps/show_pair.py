"""What `xvoe show` does: a video and its pair partner as a contact sheet (PNG), an animation
(GIF), or a clip for slides and a class (MP4), with the pair's surprise curves under it.
"""
from __future__ import annotations

import errno
from pathlib import Path

import h5py
import imageio_ffmpeg
import matplotlib.pyplot as plt
import numpy as np

from ..errors import XvoeError
from ..evaluation.score_curves import read_curves
from ..evaluation.score_headers import check_same_split, warn_unchecked
from ..evaluation.score_tables import read_scores
from ..fingerprints import split_identity
from ..outputs import atomic_paths, claim_file, claim_scope, nearly_full
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE, check_display_size
from ..scenes.videos import check_index, describe, video_indices, wall_lowered
from .curves import definition_curves, draw_pair_curves, member_labels
from .frames import display_rows, save_figure, save_gif, show_video

__all__ = ["show", "save_video"]


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
        labels = member_labels([bool(file["possible"][i]) for i in indices])
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
