"""Hand-made VoE events (xvoe.custom): physics of one case, the saved file, clear errors."""
import numpy as np
import pytest

from xvoe.errors import XvoeError
from xvoe.scenes import custom, store
from xvoe.scenes.render import STATE_COLUMNS
from xvoe.scenes.videos import find_pair

SPEED = 50.0


def collision(**kwargs):
    """A ball rolls into a resting ball behind a wall; member 1 passes through it."""
    things = [custom.ball(4, vx=SPEED), custom.ball(34), custom.wall(32, half_width=12, height=18)]
    return custom.make_pair(things, custom.pass_through(0, 1), **kwargs)


def test_a_hand_made_collision_obeys_the_physics_and_its_violation_does_not():
    pair = collision(wall="S3")
    event = pair.event_frame
    assert 1 <= event < 14 and pair.expected.event_frame == event and pair.setting == "S3"
    x_expected = pair.expected.trajectory.position[..., 0]
    x_impossible = pair.impossible.trajectory.position[..., 0]
    np.testing.assert_array_equal(x_expected[:event], x_impossible[:event])   # one simulation until the edit
    # Newton's cradle: the incoming ball stops, the hit one rolls on at its speed
    velocity = pair.expected.trajectory.velocity[-1, :2, 0]
    np.testing.assert_allclose(velocity, [0.0, SPEED], atol=1e-6)
    assert x_expected[-1, 0] < x_expected[-1, 1] - 8 + 0.5          # never further than touching
    # the violation: the incoming ball goes on through the resting one, which does not move
    np.testing.assert_allclose(pair.impossible.trajectory.velocity[-1, :2, 0], [SPEED, 0.0], atol=1e-6)
    assert x_impossible[-1, 0] > x_impossible[-1, 1] + 8
    assert pair.expected.possible and not pair.impossible.possible


def test_a_saved_pair_is_a_test_split_in_the_stored_schema(tmp_path):
    pair = collision(wall="away_start_end", frames=12)
    path = pair.save(tmp_path / "mine.h5", size=32)
    with store.open_dataset(path) as file:
        assert file.attrs["split"] == "test"
        assert file["rgbd"].shape == (2, 12, 32, 32, 4) and file["rgbd"].dtype == np.uint8
        assert file["ids"].shape == (2, 12, 32, 32)
        assert file["states"].shape == (2, 12, 8, len(STATE_COLUMNS))
        assert list(store.strings(file, "setting")) == ["S1", "S1"]
        assert list(file["possible"][:]) == [True, False]
        assert list(file["event_frame"][:]) == [pair.event_frame] * 2
        assert find_pair(file, "custom", "S1", 0) == (0, 1)
        # the members differ only from the event frame on
        rgbd = file["rgbd"][:]
        event = pair.event_frame
        np.testing.assert_array_equal(rgbd[0, :event], rgbd[1, :event])
        assert (rgbd[0, event:] != rgbd[1, event:]).any()
        # three things: two balls and a wall, in the same slots in both members
        names = list(file.attrs["kind_names"])
        assert sorted(names[k] for k in file["kind"][0] if k) == ["ball", "ball", "wall"]
        np.testing.assert_array_equal(file["kind"][0], file["kind"][1])
    with pytest.raises(XvoeError, match="exists"):
        pair.save(path, size=32)


def test_remove_and_teleport_happen_at_their_frame():
    things = [custom.cube(20, fixed=True), custom.ball(40), custom.wall(30, half_width=16, height=20)]
    removed = custom.make_pair(things, custom.remove(0, 6), wall="S2")
    assert removed.event_frame == 6
    assert removed.impossible.trajectory.present[:6, 0].all() and not removed.impossible.trajectory.present[6:, 0].any()
    moved = custom.make_pair(things, custom.teleport(1, 3, dx=10))
    x = moved.impossible.trajectory.position[:, 1, 0]
    assert x[2] == 40 and x[3] == pytest.approx(50)


@pytest.mark.parametrize("things, violation, kwargs, message", [
    ([custom.ball(10, vx=50), custom.ball(12)], custom.pass_through(0, 1), {}, "overlap"),
    ([custom.ball(10, vx=-50), custom.ball(40)], custom.pass_through(0, 1), {}, "never touch"),
    ([custom.ball(10, vx=50), custom.ball(40)], custom.pass_through(0, 2), {}, "things 0..1"),
    ([custom.ball(10), custom.wall(30, 10, 18)], custom.remove(1, 5), {}, "is a wall"),
    ([custom.ball(10)], custom.remove(0, 15), {}, "between 1 and 14"),
    ([custom.ball(10)], custom.remove(0, 5), {"wall": "S4"}, "wall must be"),
    ([custom.ball(10, y=5)], custom.remove(0, 5), {}, "below the floor"),
    ([("ball", 10)], custom.remove(0, 5), {}, "custom.ball"),
    ([custom.ball(10)], "remove", {}, "violation must be"),
    ([custom.ball(10 * i + 5) for i in range(9)], custom.remove(0, 5), {}, "1 to 8 things"),
])
def test_bad_input_gets_a_clear_error(things, violation, kwargs, message):
    with pytest.raises(XvoeError, match=message):
        custom.make_pair(things, violation, **kwargs)


def test_bad_size_gets_a_clear_error(tmp_path):
    with pytest.raises(XvoeError, match="size must be"):
        collision().save(tmp_path / "x.h5", size=8)
