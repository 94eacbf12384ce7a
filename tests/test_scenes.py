"""Invariants of the scene samplers, for any seed and frame count (hypothesis)."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from xvoe.scenes.render import render
from xvoe.scenes.scenarios import SCENARIOS, TEST_SETTINGS, TRAINING_GROUPS, behind, continuity, permanence
from xvoe.scenes.world import FLOOR, MAX_SLOTS, OBJECT_SIZE, WORLD, _frame_time, ball, wall_fraction

seeds = st.integers(0, 2**32 - 1)
frame_counts = st.integers(10, 40)


def covered(thing, wall, margin=0.0):
    """Is `thing` (a ball or cube at its spec position) inside the wall's silhouette?"""
    return (abs(thing.x - wall.x) + thing.size + margin <= wall.half_width
            and thing.y + thing.size <= FLOOR + wall.height)


@settings(max_examples=60, deadline=None)
@given(seeds)
def test_hidden_thing_and_meeting_point_are_behind_the_wall(seed):
    scene = behind.sample(np.random.default_rng(seed), ball)
    incoming, hidden, wall = (scene.things[i] for i in (behind._INCOMING, behind._HIDDEN, behind._WALL))
    assert covered(hidden, wall, margin=1.0)
    meeting = type(incoming)(**{**incoming.__dict__, "x": hidden.x - 2 * OBJECT_SIZE})
    assert covered(meeting, wall, margin=1.0)
    assert 0 <= incoming.x < wall.x - wall.half_width      # starts in view, left of the wall
    assert incoming.vx > 0


@settings(max_examples=60, deadline=None)
@given(seeds)
def test_colours_and_slots(seed):
    rng = np.random.default_rng(seed)
    for module in SCENARIOS.values():
        scene = module.sample(rng)
        colors = np.array([scene.background, scene.floor] + [t.color for t in scene.things])
        distance = np.abs(colors[:, None].astype(int) - colors[None].astype(int)).sum(-1)
        assert (distance + np.eye(len(colors), dtype=int) * 999 >= 110).all()
        assert len(set(scene.slots)) == len(scene.things) and max(scene.slots) < MAX_SLOTS


@settings(max_examples=40, deadline=None)
@given(seeds)
def test_permanence_cubes_fit_behind_the_wall_apart(seed):
    scene = permanence.sample(np.random.default_rng(seed))
    wall = scene.things[permanence._WALL]
    cubes = [scene.things[i] for i in permanence._CUBES]
    xs = sorted(c.x for c in cubes)
    assert np.diff(xs).min() >= 2 * OBJECT_SIZE + 2
    assert all(abs(c.x - wall.x) + c.size + 1 <= wall.half_width for c in cubes)
    assert all(c.y > WORLD + c.size for c in cubes)     # dropped from above the picture


@settings(max_examples=40, deadline=None)
@given(seeds)
def test_continuity_window_shows_a_ball_and_sides_hide_it(seed):
    scene = continuity.sample(np.random.default_rng(seed))
    wall = scene.things[continuity._WALL]
    window_half, window_height = wall.window
    assert window_half > OBJECT_SIZE                          # a ball fits in the window
    assert wall.half_width - window_half >= 2 * OBJECT_SIZE   # each solid side hides a ball
    assert 2 * OBJECT_SIZE < window_height <= wall.height / 2  # the window is in the lower half
    rolling = scene.things[continuity._BALL]
    assert 0 <= rolling.x < wall.x - wall.half_width and rolling.vx > 0


@settings(max_examples=60, deadline=None)
@given(seeds, frame_counts, st.sampled_from(TEST_SETTINGS))
def test_events_happen_behind_a_standing_wall(seed, frames, scenario_setting):
    """The event frame exists and the wall stands on the floor at it, so the edit made in the
    step into it is out of sight; before it, both members are the same simulation."""
    scenario, setting = scenario_setting
    expected, other = SCENARIOS[scenario].test_pair(np.random.default_rng(seed), setting, frames)
    event = expected.event_frame
    if (scenario, setting) == ("permanence", "S2"):
        assert event == -1 and other.possible
        return
    assert 1 <= event < frames and other.event_frame == event
    assert wall_fraction(expected.scene.wall_schedule, _frame_time(event, frames)) == 1.0
    assert other.possible == (setting == "S2")
    both = [i for i, thing in enumerate(other.scene.things) if thing.exists]
    np.testing.assert_array_equal(expected.trajectory.position[:event, both], other.trajectory.position[:event, both])


@settings(max_examples=15, deadline=None)
@given(seeds, st.sampled_from(sorted(TRAINING_GROUPS)), st.booleans())
def test_training_videos_render_with_every_slot_in_range(seed, group, with_wall):
    take = TRAINING_GROUPS[group](np.random.default_rng(seed), with_wall, 15)
    video = render(take.scene, take.trajectory, size=32)
    assert video.rgbd.shape == (15, 32, 32, 4) and video.ids.max() <= MAX_SLOTS
    kinds = {int(k) for k in video.kind if k}
    has_wall = bool(kinds & {3, 4})
    assert has_wall == with_wall
    visible = video.states[..., 6]
    assert visible.min() >= 0 and visible.max() <= 1
    # training shows no hidden objects: the wall is away at the start and the end
    assert (visible.max(axis=0)[video.kind > 0] > 0).all()
