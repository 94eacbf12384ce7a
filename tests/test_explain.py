"""Explanation masks against ground-truth silhouettes."""
import numpy as np

from xvoe.benchmark.render import STATE_COLUMNS
from xvoe.benchmark.videos import silhouette
from xvoe.evaluation.explain import decoded_mask, iou


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
