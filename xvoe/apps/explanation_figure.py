"""The explanation figure (the paper's Fig. 7/8): what the model believes is behind the wall,
row by row, and drawn onto the scene at its display size, each hypothesis only as far as its
probability.
"""
from __future__ import annotations

import textwrap

import matplotlib.pyplot as plt
import numpy as np
from PIL import Image

from ..evaluation.explain import DRAW_THRESHOLD, Explanation, drawn_pixels
from ..scenes.display import enlarge, outline
from .frames import SHEET_FONT, cell_inches, draw_frame_rows

__all__ = ["OUTLINE_COLORS", "plot_explanation", "BARELY_APART", "explanation_overlay", "outline_color"]


# The outline of the model's hidden object: scene colours are drawn at random from all of RGB
# (xvoe.scenes.world.sample_colors), so each figure takes the one of these farthest from its scene's.
OUTLINE_COLORS = {"magenta": (255, 0, 255), "cyan": (0, 255, 255), "orange": (255, 128, 0), "blue": (0, 0, 255),
                  "red": (255, 0, 0), "yellow": (255, 255, 0), "green": (0, 160, 0), "purple": (128, 0, 255)}


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
    notes = explanation.notes() + _alike_note(rows)
    if explanation.display is not None:
        size = explanation.display.shape[1]
        scene, colour = explanation_overlay(explanation)
        # a display that is the model's frames enlarged is the observed row already, outlined
        shown = [row for row in rows if explanation.display_resimulated or row[0] != "observed"]
        rows = [("scene", _scene_label(explanation, size, colour), scene),
                *((kind, name, enlarge(video, size)) for kind, name, video in shown)]
    cell = _row_inches(rows)
    frames_width = explanation.observed.shape[0] * cell         # the labels take their own width beside it
    width = max(4.0, frames_width + _label_inches(rows))
    title = _fitted(explanation.title, frames_width, SHEET_FONT + 1)      # centred over the frames
    notes = _fitted("\n".join(notes), frames_width, SHEET_FONT)
    lines = title.count("\n") + 1 + (notes.count("\n") + 1 if notes else 0)
    fig, ax = plt.subplots(figsize=(width, len(rows) * cell + 0.3 + 0.25 * lines))
    draw_frame_rows(ax, [video for _, _, video in rows], [name for _, name, _ in rows], title)
    if notes:
        ax.set_xlabel(notes, fontsize=SHEET_FONT, labelpad=6)
    fig.tight_layout()
    fig.drawn_rows = [(kind, name) for kind, name, _ in rows]     # what was drawn, for a reader to check
    return fig


def _row_inches(rows: list[tuple[str, str, np.ndarray]]) -> float:
    """Inches a row of frames takes: a frame's (`cell_inches`), or more where the tallest label
    needs it, so that no label runs into the next row's (a line is 1.2 times the font's size)."""
    lines = max(label.count("\n") + 1 for _, label, _ in rows)
    return max(cell_inches(rows[0][2].shape[1]), lines * 1.2 * SHEET_FONT / 72 + 0.1)


def _label_inches(rows: list[tuple[str, str, np.ndarray]]) -> float:
    """Inches the widest row label takes beside the frames."""
    return max(len(line) for _, label, _ in rows for line in label.split("\n")) * 0.6 * SHEET_FONT / 72 + 0.2


def _fitted(text: str, width: float, points: float) -> str:
    """`text` with each line wrapped to `width` inches at a font of `points` (a character is at
    most 0.6 of the font's size wide), so that no line runs off the figure."""
    characters = max(20, int(width * 72 / (0.6 * points)))
    return "\n".join(textwrap.fill(line, characters) for line in text.split("\n")) if text else text


# a hypothesis whose object stays this share of the frame's width from the mean's, in every frame,
# barely differs from it (1/16: two pixels at 32x32, about an object's radius)
BARELY_APART = 1 / 16


def _alike_note(rows: list[tuple[str, str, np.ndarray]]) -> list[str]:
    """A line naming the hypotheses drawn that barely differ from the mean (`BARELY_APART`), and
    how far apart they are: rows that look alike are not to be read as rival stories."""
    mean = next((video for kind, _, video in rows if kind == "hidden object"), None)
    alike = {}
    for kind, label, video in rows:
        apart = _apart(video, mean) if kind == "hypothesis" and mean is not None else None
        if apart is not None and apart <= BARELY_APART * video.shape[2]:
            alike[label.split(":")[0]] = apart
    if not alike:
        return []
    numbers = ", ".join(name.removeprefix("hypothesis ") for name in alike)
    one = len(alike) == 1
    return [f"{'hypothesis' if one else 'hypotheses'} {numbers} barely {'differs' if one else 'differ'} from "
            f"the mean: {'its object stays' if one else 'their objects stay'} within {max(alike.values()):.1f} "
            f"pixels (of {rows[0][2].shape[2]}) of the mean's in every frame"]


def _apart(video: np.ndarray, mean: np.ndarray) -> float | None:
    """The largest distance in pixels, over frames, between the centres of the objects two
    decoded rows (T, H, W, 4) draw; None where a frame holds an object in one row alone."""
    drawn, other = drawn_pixels(video), drawn_pixels(mean)
    if (drawn.any(axis=(1, 2)) != other.any(axis=(1, 2))).any():
        return None
    apart = [np.linalg.norm(np.mean(np.nonzero(a), axis=1) - np.mean(np.nonzero(b), axis=1))
             for a, b in zip(drawn, other) if a.any()]
    return max(apart, default=0.0)


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
