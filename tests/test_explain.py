"""Explanation masks against ground-truth silhouettes, and the explanation figure against its numbers."""
from dataclasses import replace

import numpy as np
import pytest

from xvoe.evaluation.explain import decoded_mask, iou
from xvoe.scenes.render import STATE_COLUMNS
from xvoe.scenes.videos import silhouette


def test_silhouette_matches_the_rendered_ids(test_data):
    """A fully visible ball or cube's rasterised silhouette is exactly its id pixels."""
    names = test_data["kind_names"]
    checked = 0
    for video in range(0, len(test_data["kind"]), 7):
        for slot in range(8):
            kind = names[test_data["kind"][video, slot]]
            if kind not in ("ball", "cube"):
                continue
            mask = silhouette(test_data["states"][video, :, slot], list(STATE_COLUMNS), kind, 64)
            visible = test_data["states"][video, :, slot, STATE_COLUMNS.index("visible")]
            for t in np.flatnonzero(visible == 1.0):
                np.testing.assert_array_equal(mask[t], test_data["ids"][video, t] == slot + 1)
                checked += 1
    assert checked > 100


def test_iou_and_decoded_mask():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    a[:2, :2] = True
    b[:2, :] = True
    assert iou(a, b) == 0.5 and iou(a, a) == 1.0 and iou(~a & a, ~b & b) == 1.0
    pictures = np.full((2, 4, 3, 3), 1.5, np.float32)   # blank everywhere...
    pictures[1, 3, 1, 1] = 0.0                           # ...but one object pixel in the second
    masks = decoded_mask(pictures)
    assert masks.shape == (2, 3, 3) and masks.sum() == 1 and masks[1, 1, 1]


# --- the explanation figure draws what the numbers say ------------------------------------

def _frames(value: int, frames: int = 3, size: int = 8) -> np.ndarray:
    return np.full((frames, size, size, 4), value, np.uint8)


def _object(frames: int = 3, size: int = 8, at: int = 2) -> np.ndarray:
    """A decoded slot that draws a 3x3 square on the blank, from pixel (at, at)."""
    pictures = _frames(255, frames, size)
    pictures[:, at:at + 3, at:at + 3] = (200, 0, 0, 0)
    return pictures


def _nll(p_hidden: float, p_two: float, display: bool = False, hypotheses=None):
    from xvoe.inference.explain import NLLExplanation
    scene = _frames(100)
    two = {"two_objects": _frames(90), "two_objects_empty": _frames(80), "twin_from": 2} if p_two is not None else {}
    extra = {"display": np.full((3, 32, 32, 4), 100, np.uint8)} if display else {}
    return NLLExplanation(scene, _frames(120), _object(), 3, "hand-made", p_hidden, p_two or 0.0, 5.0, 100.0, 64,
                          40, 7.5, hypotheses or [("hypothesis 1: 0.50", _object(at=3)),
                                                  ("hypothesis 2: 0.40", _object(at=4))],
                          behind_empty=_frames(110), **two, **extra)


def _kinds(explanation) -> list[str]:
    import matplotlib.pyplot as plt

    from xvoe.apps.explanation_figure import plot_explanation
    figure = plot_explanation(explanation)
    kinds = [kind for kind, _ in figure.drawn_rows]
    assert len(figure.axes[0].get_yticklabels()) == len(kinds)
    plt.close(figure)
    return kinds


def test_the_figure_at_the_models_size_keeps_its_labels_apart_and_its_title_on_the_figure():
    """At 32x32 with no display, five-line row labels and a long title once ran into each other
    and off the figure."""
    import matplotlib.pyplot as plt

    from xvoe.apps.explanation_figure import plot_explanation
    explanation = replace(_nll(0.9, 0.0), title="blocking S3 pair 16 member 1 (impossible)\nESS 6.3 of the 128 "
                          + "samples holding an object (drawn 64 for each explanation: one object, two identical "
                          + "ones); the hypotheses' latents differ most at frames 14, 13, 12" * 2)
    figure = plot_explanation(explanation)
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    labels = sorted((label.get_window_extent(renderer) for label in figure.axes[0].get_yticklabels()),
                    key=lambda box: box.y0)
    assert len(labels) >= 4 and all(lower.y1 <= upper.y0 for lower, upper in zip(labels, labels[1:]))
    title, page = figure.axes[0].title.get_window_extent(renderer), figure.bbox
    assert page.x0 <= title.x0 and title.x1 <= page.x1
    plt.close(figure)


@pytest.mark.parametrize("p_hidden", [0.0, 0.9])
@pytest.mark.parametrize("p_two", [None, 0.0, 0.9])
def test_the_figure_draws_each_hypothesis_exactly_where_its_probability_exceeds_the_threshold(p_hidden, p_two):
    from xvoe.evaluation.explain import DRAW_THRESHOLD
    explanation = _nll(p_hidden, p_two)
    kinds = _kinds(explanation)
    hidden = p_hidden > DRAW_THRESHOLD
    assert ("hidden object" in kinds) == hidden and kinds.count("hypothesis") == (2 if hidden else 0)
    assert ("two objects" in kinds) == (p_two is not None and p_two > DRAW_THRESHOLD)
    assert ("behind the wall" in kinds) == (p_two is None or 1 - p_two > DRAW_THRESHOLD)
    assert kinds[0] == "observed"
    assert ("no hidden object: p(hidden object) = 0.00" in explanation.notes()) == (not hidden)
    if not hidden:      # the scene without the hidden object, no label counting samples
        rows = {kind: (label, frames) for kind, label, frames in explanation.figure_rows()}
        if "behind the wall" in rows:
            assert (rows["behind the wall"][1] == 110).all()
        if "two objects" in rows:
            assert (rows["two objects"][1] == 80).all()
    else:               # drawn at opacity p, the samples counted as the ESS shown counts them
        rows = {kind: (label, frames) for kind, label, frames in explanation.figure_rows()}
        if "behind the wall" in rows:
            assert (rows["behind the wall"][1] == 119).all()           # 0.9 * 120 + 0.1 * 110
        assert "the 40 samples" in rows["hidden object"][0] and "ESS 7.5" in rows["hidden object"][0]


def test_hypotheses_that_draw_like_the_mean_are_named_not_drawn_and_rows_are_masked():
    haze = _object(at=4)
    haze[:, :2, :2] = (250, 250, 0, 250)      # the decoder's colour where its depth says nothing is drawn
    explanation = _nll(0.9, None, hypotheses=[("hypothesis 1: 0.50", _object()), ("hypothesis 2: 0.40", haze)])
    rows = [(kind, frames) for kind, _, frames in explanation.figure_rows()]
    assert [kind for kind, _ in rows].count("hypothesis") == 1
    assert "hypothesis 1: drawn as the mean or a heavier hypothesis, not shown again" in explanation.notes()
    drawn = dict(rows)["hypothesis"]
    assert (drawn[:, :2, :2] == 255).all() and (drawn[:, 4:7, 4:7, 0] == 200).all()


def test_the_scene_outlines_a_hidden_object_only_above_the_threshold():
    from xvoe.apps.explanation_figure import explanation_overlay
    believed, colour = explanation_overlay(_nll(0.9, None, display=True))
    assert colour is not None and (believed != 100).any()
    doubted, colour = explanation_overlay(_nll(0.0, None, display=True))
    assert colour is None and (doubted == 100).all()
    kinds = _kinds(_nll(0.0, None, display=True))
    assert kinds == ["scene", "observed", "behind the wall"]


def test_an_mse_explanation_whose_slot_draws_nothing_says_nothing_hidden():
    from xvoe.evaluation.explain import Explanation
    empty = Explanation(_frames(100), _frames(100), _frames(255), 2, "kept, draws nothing")
    drawn = Explanation(_frames(100), _frames(100), _object(), 2, "kept, draws a square")
    assert not empty.draws_hidden and drawn.draws_hidden
    assert [label for label, _ in empty.rows()][-1] == "nothing hidden"
    assert _kinds(empty)[-1] == "nothing hidden" and _kinds(drawn)[-1] == "hidden object"
    assert "nothing hidden" not in [label for label, _ in drawn.rows()]


def test_every_nll_figure_of_a_fresh_split_draws_its_rows_where_the_score_file_puts_them(tmp_path):
    """The shipped xpl on a fresh split of one pair a setting: a video's NLL figure, drawn with
    the score file's settings and seed, draws "hidden object" iff the file's p_hidden exceeds
    DRAW_THRESHOLD and "two objects" iff its p_two does; read on the videos that draw each row and
    on neighbours that draw neither (all 440 of a 20-pair split: benchmarks/explanation_rows.py)."""
    import xvoe
    from xvoe.apps.rows import DrawnRows, explanation_rows
    data = str(tmp_path / "fresh.h5")
    xvoe.generate(xvoe.GenerateConfig(split="test", pairs=1, size=32, seed=2026), data)
    scores = xvoe.score("xpl", data, tmp_path / "nll.csv", surprise="nll", progress=False)
    chosen = [0, 8, 9, 11, 18, 19]
    found = explanation_rows("xpl", data, scores, indices=chosen, display_size=None)
    assert [rows.index for rows in found] == chosen
    assert [rows.index for rows in found if rows.disagree] == []
    drawn = {kind: [rows.index for rows in found if rows.drawn[kind]] for kind in ("hidden object", "two objects")}
    assert drawn == {"hidden object": [8], "two objects": [11, 19]}    # blocking S2 0; blocking S3 1, continuity S2 1
    flipped = [DrawnRows(rows.index, {kind: 1 - p for kind, p in rows.probability.items()}, rows.drawn)
               for rows in found]
    assert all(rows.disagree for rows in flipped)       # a figure against the opposite numbers is named
    mse = xvoe.score("random", data, tmp_path / "random.csv", progress=False)
    with pytest.raises(xvoe.XvoeError, match="has no NLL columns"):
        explanation_rows("xpl", data, mse)
