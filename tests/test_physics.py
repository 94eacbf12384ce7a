"""Physics validity, read back from the saved states of generated videos."""
import numpy as np
import pytest
from conftest import column, videos_of

from xvoe.scenes.scenarios import TEST_SETTINGS

TOLERANCE = 0.5   # pixels at 64x64: how far one substep may carry a ball into another


def solid_slots(data, video):
    names = data["kind_names"]
    return [k for k in range(data["kind"].shape[1]) if names[data["kind"][video, k]] in ("ball", "cube")]


def penetration(data, video, a, b, t):
    """How deep objects in slots a and b overlap at frame t (pixels; <= 0: apart)."""
    names = data["kind_names"]
    x, y, size = column(data, "x")[video, t], column(data, "y")[video, t], column(data, "size")[video, t]
    kinds = names[data["kind"][video, a]], names[data["kind"][video, b]]
    dx, dy = abs(x[a] - x[b]), abs(y[a] - y[b])
    if kinds == ("ball", "ball"):
        return size[a] + size[b] - np.hypot(dx, dy)
    if kinds == ("cube", "cube"):
        return min(size[a] + size[b] - dx, size[a] + size[b] - dy)
    ball, box = (a, b) if kinds[0] == "ball" else (b, a)
    gap_x = max(abs(x[ball] - x[box]) - size[box], 0.0)
    gap_y = max(abs(y[ball] - y[box]) - size[box], 0.0)
    return size[ball] - np.hypot(gap_x, gap_y)


def deepest_overlap(data, video):
    present = column(data, "present")[video]
    slots = solid_slots(data, video)
    depth = -np.inf
    for t in range(present.shape[0]):
        for i, a in enumerate(slots):
            for b in slots[i + 1:]:
                if present[t, a] and present[t, b]:
                    depth = max(depth, penetration(data, video, a, b, t))
    return depth


def test_no_interpenetration_in_possible_videos(test_data):
    possible = np.flatnonzero(test_data["possible"])
    assert len(possible) > 0
    for video in possible:
        assert deepest_overlap(test_data, video) < TOLERANCE, video


@pytest.mark.parametrize("scenario", ["collision", "blocking"])
def test_impossible_member_passes_through(test_data, scenario):
    for setting in ("S1", "S3"):
        for video in videos_of(test_data, scenario, setting, member=1):
            assert not test_data["possible"][video]
            assert deepest_overlap(test_data, video) > 2.0   # well inside each other


def moving_ball_speeds(data, video):
    """vx of every ball slot over time, (T, balls)."""
    names = data["kind_names"]
    balls = [k for k in range(8) if names[data["kind"][video, k]] == "ball"]
    return column(data, "vx")[video][:, balls]


def test_collision_exchanges_velocities(test_data):
    for setting in ("S1", "S2", "S3"):
        for video in videos_of(test_data, "collision", setting, member=0):
            vx = moving_ball_speeds(test_data, video)
            event = test_data["event_frame"][video]
            before, after = vx[event - 1], vx[event + 1]
            incoming = np.argmax(np.abs(before))
            assert abs(before[1 - incoming]) < 1e-6 and abs(before[incoming]) > 3.0
            np.testing.assert_allclose(after[incoming], 0.0, atol=1e-6)         # stops
            np.testing.assert_allclose(after[1 - incoming], before[incoming], rtol=1e-3)   # rolls on


def test_blocking_ball_reverses(test_data):
    for setting in ("S1", "S2", "S3"):
        for video in videos_of(test_data, "blocking", setting, member=0):
            vx = moving_ball_speeds(test_data, video)[:, 0]
            event = test_data["event_frame"][video]
            assert abs(vx[event - 1]) > 3.0
            np.testing.assert_allclose(vx[event + 1], -vx[event - 1], rtol=1e-3)


def cube_slots(data, video):
    return [k for k in range(8) if data["kind_names"][data["kind"][video, k]] == "cube"]


def visible_cubes_at_end(data, video):
    return int((column(data, "visible")[video, -1, cube_slots(data, video)] > 0.5).sum())


def test_permanence_keeps_its_cubes(test_data):
    for setting, member in (("S1", 0), ("S2", 0), ("S2", 1)):
        for video in videos_of(test_data, "permanence", setting, member):
            assert visible_cubes_at_end(test_data, video) == 3
            assert column(test_data, "present")[video, -1, cube_slots(test_data, video)].sum() == 3


def test_permanence_impossible_member_loses_a_cube(test_data):
    for video in videos_of(test_data, "permanence", "S1", member=1):
        assert visible_cubes_at_end(test_data, video) < 3
        event = test_data["event_frame"][video]
        present = column(test_data, "present")[video]
        removed = np.flatnonzero(present[event - 1] > present[event])
        assert len(removed) == 1
        # it was taken away out of sight, behind the standing wall
        assert column(test_data, "visible")[video, event - 1, removed[0]] == 0.0


def behind_wall_visibility(data, video):
    """Visible fraction of the ball at frames where it is wholly inside the wall's span
    and the wall stands on the floor: anything seen then is seen through the window."""
    names = data["kind_names"]
    kinds = [names[k] for k in data["kind"][video]]
    ball, wall = kinds.index("ball"), kinds.index("window_wall")
    x, y = column(data, "x")[video], column(data, "y")[video]
    wall_down = np.isclose(y[:, wall], y[:, wall].max())
    size = column(data, "size")[video]
    inside = np.abs(x[:, ball] - x[:, wall]) <= size[:, wall] - size[:, ball]
    frames = wall_down & inside
    assert frames.any()
    return column(data, "visible")[video, frames, ball]


def test_continuity_ball_shows_in_window_only_when_possible(test_data):
    for setting in ("S1", "S2", "S3"):
        for video in videos_of(test_data, "continuity", setting, member=0):
            assert behind_wall_visibility(test_data, video).max() > 0.3
        for video in videos_of(test_data, "continuity", setting, member=1):
            assert behind_wall_visibility(test_data, video).max() == 0.0
            assert test_data["possible"][video] == (setting == "S2")


@pytest.mark.parametrize("scenario,setting", [s for s in TEST_SETTINGS if s[1] != "S2"])
def test_impossible_member_matches_expected_before_event(test_data, scenario, setting):
    for video in videos_of(test_data, scenario, setting, member=1):
        expected = video - 1
        event = test_data["event_frame"][video]
        assert event == test_data["event_frame"][expected] and 1 <= event
        np.testing.assert_array_equal(test_data["rgbd"][video, :event], test_data["rgbd"][expected, :event])
        np.testing.assert_array_equal(test_data["states"][video, :event], test_data["states"][expected, :event])
        assert not np.array_equal(test_data["states"][video, event:], test_data["states"][expected, event:])


def test_hidden_thing_in_s2_is_unseen_until_it_moves(test_data):
    """S2 member 0: the wall stands throughout. The fixed cube is visible in no frame; the
    hidden ball is unseen until the collision sends it out from behind the wall."""
    names = test_data["kind_names"]
    for scenario in ("collision", "blocking"):
        for video in videos_of(test_data, scenario, "S2", member=0):
            visible = column(test_data, "visible")[video]
            vx = column(test_data, "vx")[video]
            solid = [k for k in range(8) if names[test_data["kind"][video, k]] in ("ball", "cube")]
            hidden = [k for k in solid if vx[0, k] == 0.0]
            assert len(hidden) == 1
            event = test_data["event_frame"][video]
            assert visible[:event, hidden[0]].max() == 0.0
            if scenario == "blocking":
                assert visible[:, hidden[0]].max() == 0.0
            else:
                assert visible[event:, hidden[0]].max() > 0.5


def test_settings_of_one_pair_index_share_the_scene(test_data):
    """S2 and S3 pairs of one index differ only in the wall's timetable: until it is lifted
    their objects move identically."""
    columns = test_data["columns"]
    for scenario in ("collision", "blocking", "continuity"):
        for member in (0, 1):
            s2, s3 = videos_of(test_data, scenario, "S2", member), videos_of(test_data, scenario, "S3", member)
            for a, b in zip(s2, s3):
                assert test_data["pair"][a] == test_data["pair"][b]
                shown = test_data["kind"][a] > 0        # S2 member 1 may leave the hidden slot empty
                assert np.array_equal(test_data["color"][a][shown], test_data["color"][b][shown])
                np.testing.assert_array_equal(test_data["rgbd"][a, :12], test_data["rgbd"][b, :12])
                moving = [columns.index(c) for c in ("x", "vx", "present")]
                np.testing.assert_array_equal(test_data["states"][a][:, shown][..., moving],
                                              test_data["states"][b][:, shown][..., moving])
