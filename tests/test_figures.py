"""What the figures draw, read off the figures themselves: frames large enough to read, an edge
round every frame, charts whose captions and panels say what their numbers mean."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.collections import PatchCollection

from xvoe.apps.curves import _plain
from xvoe.apps.explanation_figure import plot_explanation
from xvoe.apps.frames import contact_sheet
from xvoe.apps.metric_plots import plot_comparative, plot_holistic
from xvoe.inference.explain import NLLExplanation


def _row(metric, scenario, setting, value, ideal, low=None, high=None):
    return {"model": "xpl", "metric": metric, "column": "score", "scenario": scenario, "setting": setting,
            "value": value, "low": value if low is None else low, "high": value if high is None else high,
            "count": 4, "ideal": ideal, "p": 1.0}


def test_the_comparative_panel_below_counts_either_side_of_the_ideal_as_off():
    """In S2 (ideal 50%) 100% is as far off as 0%: both bars hang 50 points below the line."""
    rows = [_row("comparative", "blocking", "S1", 1.0, 1.0, 0.51, 1.0),
            _row("comparative", "blocking", "S2", 1.0, 0.5, 0.51, 1.0),
            _row("comparative", "collision", "S2", 0.0, 0.5, 0.0, 0.49)]
    figure = plot_comparative(rows)
    below = figure.axes[1]
    assert [round(bar.get_height()) for bar in below.patches] == [0, -50, -50]
    assert all(y <= 0 for line in below.lines for y in line.get_ydata())     # no interval above the ideal
    plt.close(figure)


def test_holistic_groups_name_the_settings_each_scenario_has():
    figure = plot_holistic([_row("holistic", "permanence", "", 0.8, 1.0), _row("holistic", "blocking", "", 0.9, 1.0)])
    ticks = [tick.get_text() for tick in figure.axes[0].get_xticklabels()]
    assert ticks == ["permanence\nS1-S2\n(n=4)", "blocking\nS1-S3\n(n=4)"]
    plt.close(figure)


def test_a_sheet_of_the_models_small_frames_draws_each_about_an_inch_wide():
    frames = 6
    rgbd = np.zeros((1, frames, 32, 32, 4), np.uint8)
    figure = contact_sheet(rgbd, np.zeros((1, frames, 32, 32), np.int64), ["a video"])
    assert figure.get_size_inches()[0] / frames >= 1.0
    edges = [c for c in figure.axes[0].collections if isinstance(c, PatchCollection)]
    assert len(edges) == 1 and len(edges[0].get_paths()) == 3 * frames     # RGB, depth, ids rows
    plt.close(figure)


def _object(frames: int, x: int) -> np.ndarray:
    """A decoded slot (T, 32, 32, 4): a 4x4 green square at column x on white, far depth elsewhere."""
    picture = np.full((frames, 32, 32, 4), 255, np.uint8)
    picture[:, 10:14, x:x + 4] = (0, 200, 0, 0)
    return picture


def test_hypotheses_that_barely_differ_from_the_mean_are_named_so_under_the_figure():
    frames = 3
    blank = np.full((frames, 32, 32, 4), 255, np.uint8)
    mean = _object(frames, 10)
    explanation = NLLExplanation(blank, blank, mean, 2, "a video", p_hidden=1.0, holding=8, holding_ess=4.0,
                                 hypotheses=[("hypothesis 1: 0.5", _object(frames, 11)),
                                             ("hypothesis 2: 0.3", _object(frames, 22))])
    figure = plot_explanation(explanation)
    notes = " ".join(figure.axes[0].get_xlabel().split())      # wrapped to the figure's width
    assert "hypothesis 1 barely differs from the mean" in notes and "within 1.0 pixels" in notes
    assert "hypothesis 2" not in notes
    assert [kind for kind, _ in figure.drawn_rows].count("hypothesis") == 2
    plt.close(figure)


@pytest.mark.parametrize("value, shown", [(1063.4, "1063"), (-152.6, "-153"), (52.61, "52.6"), (0.01234, "0.0123"),
                                          (0.0, "0")])
def test_curve_titles_print_numbers_in_plain_digits(value, shown):
    """The sums and maxima over a pair's curves, in the panels' titles: 1063, not 1.06e+03."""
    assert _plain(value) == shown
