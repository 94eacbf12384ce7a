"""Continuity: a ball rolls behind a wall with a window in its lower half.

Member 0: the ball is seen in the window. Member 1: at the frame it would enter the window
it is moved past it (so it is never seen there and comes out early): impossible in S1 and
S3, where the wall is away at the start or the end and shows one ball; possible in S2,
where a second, identical ball hidden behind the wall's right part could explain it.
"""
from __future__ import annotations

import numpy as np

from ..physics import Take, run
from ..world import OBJECT_SIZE as R
from ..world import Edit, Scene, ball, make_scene, wall

__all__ = ["SETTINGS", "sample", "test_pair", "training"]

SETTINGS = ("S1", "S2", "S3")
_SCHEDULES = {"S1": "away_start_end", "S2": "stays", "S3": "away_end"}
_BALL, _WALL = 0, 1


def sample(rng: np.random.Generator) -> Scene:
    wall_x = rng.uniform(30.0, 34.0)
    window_half = rng.uniform(5.5, 6.5)                       # the window is wider than a ball
    half_width = window_half + 2 * R + rng.uniform(1.5, 3.0)  # each solid side hides a ball
    height = rng.uniform(24.0, 30.0)
    window_height = rng.uniform(2 * R + 2, min(height / 2, 12.0))
    speed = rng.uniform(48.0, 56.0)
    entry_x = wall_x - window_half - R       # where the ball starts to show in the window
    enter_time = rng.uniform(0.32, min(0.45, entry_x / speed))   # wall down, ball starts in view
    start_x = entry_x - speed * enter_time
    things = [ball(start_x, speed), wall(wall_x, half_width, height, window=(window_half, window_height))]
    return make_scene(rng, things)


def _window_entry(take: Take) -> int:
    """The first frame at which the ball reaches the window's near edge."""
    scene = take.scene
    window_left = scene.things[_WALL].x - scene.things[_WALL].window[0]
    reached = take.trajectory.position[:, _BALL, 0] + R > window_left
    return int(np.argmax(reached)) if reached.any() else -1


def _skip_window(take: Take, frame: int) -> Edit:
    """Move the ball so that at `frame` it sits just past the window, behind the wall."""
    wall_thing = take.scene.things[_WALL]
    target = wall_thing.x + wall_thing.window[0] + R + 0.5
    return Edit(frame, "teleport", _BALL, dx=target - take.trajectory.position[frame, _BALL, 0])


def test_pair(rng: np.random.Generator, setting: str, frames: int) -> tuple[Take, Take]:
    scene = sample(rng).with_schedule(_SCHEDULES[setting])
    expected = run(scene, frames)
    event = _window_entry(expected)
    expected.event_frame = event
    other = run(scene.with_edits(_skip_window(expected, event)), frames,
                possible=(setting == "S2"), event_frame=event)
    return expected, other


def training(rng: np.random.Generator, with_wall: bool, frames: int) -> Take:
    scene = sample(rng).with_schedule("away_start_end")
    return run(scene if with_wall else scene.without(_WALL), frames)
