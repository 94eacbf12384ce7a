"""The explanation measures' parts on hand-drawn masks and a generated split."""
import numpy as np
import pytest

from xvoe.evaluation.explanation_quality import _video_iou, expected_videos, ground_truth, pick, principal_spread
from xvoe.scenes import store
from xvoe.scenes.videos import silhouette


def square(size, top, left, side):
    mask = np.zeros((size, size), dtype=bool)
    mask[top:top + side, left:left + side] = True
    return mask


def test_iou_of_hand_drawn_masks():
    # two 2x2 squares one column apart: they share 2 pixels of 6
    first, second = square(4, 0, 0, 2), square(4, 0, 1, 2)
    assert _video_iou(first[None], second[None]) == pytest.approx(2 / 6)
    # a frame where both draw nothing counts 1: the mean over the two frames is (1/3 + 1) / 2
    empty = np.zeros((4, 4), dtype=bool)
    assert _video_iou(np.stack([first, empty]), np.stack([second, empty])) == pytest.approx(2 / 3)
    assert _video_iou(first[None], square(4, 2, 2, 2)[None]) == 0.0


def test_iou_of_a_cube_silhouette_shifted_by_two_pixels():
    columns = ["x", "y", "size", "present"]
    # a cube of half-size 2 centred at (5, 5) covers pixel centres 3.5..6.5: columns and rows 3..6
    states = np.array([[5.0, 5.0, 2.0, 1.0], [7.0, 5.0, 2.0, 1.0]])
    drawn = silhouette(states, columns, "cube", 12)
    assert np.array_equal(drawn[0], square(12, 3, 3, 4))
    # 4x4 against the same moved two columns: 8 shared pixels of 24
    assert _video_iou(drawn[:1], drawn[1:]) == pytest.approx(8 / 24)


def test_principal_spread_closed_form():
    # points +-a along x and +-b along y: singular values sqrt(2) a and sqrt(2) b, over sqrt(n - 1)
    a, b = 3.0, 1.0
    targets = np.array([[a, 0.0], [-a, 0.0], [0.0, b], [0.0, -b]])
    assert principal_spread(targets) == pytest.approx(np.sqrt(2 / 3) * np.array([a, b]))


def test_videos_picked_and_their_ground_truth(test_file):
    with store.open_dataset(test_file) as file:
        chosen = pick(file, "blocking", "S2", 0, 3)
        assert len(chosen) == 3
        for index in chosen:
            assert (store.strings(file, "scenario")[index], store.strings(file, "setting")[index],
                    file["member"][index]) == ("blocking", "S2", 0)
            assert ground_truth(file, index) == "hidden"      # the cube behind the wall is never seen
        assert ground_truth(file, pick(file, "collision", "S1", 0, 1)[0]) == "seen"
        expected = expected_videos(file, 8)     # 2 per scenario, the possible member of S1
        assert len(expected) == 8 and all(file["possible"][i] for i in expected)
        assert {str(s) for s in store.strings(file, "setting")[expected]} == {"S1"}
