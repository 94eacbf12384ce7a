"""Shared by collision, blocking and pass-behind: a ball rolls towards a wall behind which
something may wait, timed so that the meeting happens while the wall stands on the floor."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..physics import Take, run
from ..world import OBJECT_SIZE as R
from ..world import Edit, Scene, Thing, ball, make_scene, rolling_speed, wall

__all__ = ["sample", "test_pair", "training"]

_INCOMING, _HIDDEN, _WALL = 0, 1, 2
_SCHEDULES = {"S1": "away_start_end", "S2": "stays", "S3": "away_end"}
_WALL_HALF_WIDTH = (11.0, 14.0)   # ranges the wall's size is drawn from, world units
_WALL_HEIGHT = (14.0, 22.0)


def sample(rng: np.random.Generator, make_hidden: Callable[[float], Thing]) -> Scene:
    """Incoming ball, the hidden thing (fully covered by the wall) and the wall."""
    wall_x = rng.uniform(30.0, 36.0)
    half_width = rng.uniform(*_WALL_HALF_WIDTH)
    height = rng.uniform(*_WALL_HEIGHT)
    # The hidden thing and the incoming ball at the moment they meet both stay behind the wall.
    hidden_x = rng.uniform(wall_x - half_width + 3 * R + 1, wall_x + half_width - R - 1)
    speed = rolling_speed(rng)
    # They meet once the wall is down (0.3 s), and the incoming ball starts in view.
    meet_time = rng.uniform(0.35, min(0.5, (hidden_x - 2 * R) / speed))
    start_x = hidden_x - 2 * R - speed * meet_time
    things = [ball(start_x, speed), make_hidden(hidden_x), wall(wall_x, half_width, height)]
    return make_scene(rng, things)


def test_pair(rng: np.random.Generator, setting: str, frames: int,
              make_hidden: Callable[[float], Thing]) -> tuple[Take, Take]:
    """Member 0 meets the hidden thing; member 1 passes through it (S1, S3: impossible) or,
    in S2, finds nothing there (possible; its frames are the S3 member 1's without the reveal)."""
    scene = sample(rng, make_hidden).with_schedule(_SCHEDULES[setting])
    expected = run(scene, frames)
    event = expected.trajectory.first_contact(_INCOMING, _HIDDEN)
    expected.event_frame = event
    if setting == "S2":
        other = run(scene.without(_HIDDEN), frames, possible=True, event_frame=event)
    else:
        ghost = scene.with_edits(Edit(event, "pass_through", _INCOMING, _HIDDEN))
        other = run(ghost, frames, possible=False, event_frame=event)
    return expected, other


def training(rng: np.random.Generator, with_wall: bool, frames: int,
             make_hidden: Callable[[float], Thing] | None) -> Take:
    scene = sample(rng, make_hidden or ball)
    if make_hidden is None:
        scene = scene.without(_HIDDEN)
    scene = scene.with_schedule("away_start_end") if with_wall else scene.without(_WALL)
    take = run(scene, frames)
    if make_hidden is not None:
        take.event_frame = take.trajectory.first_contact(_INCOMING, _HIDDEN)
    return take
