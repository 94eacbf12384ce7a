"""Permanence: three cubes behind a wall in the middle; some fall, some rest on the floor.

S1: the wall comes down on an empty floor, three cubes fall behind it; when it is lifted,
member 0 shows three cubes, member 1 fewer (one was taken away once it had landed out of
sight): impossible. S2: the wall stands from the start; member 0: three cubes fall; member
1: two fall, the third was resting behind the wall all along; lifted, both show three.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..physics import Take, run
from ..world import FLOOR, Edit, Scene, cube, make_scene, wall
from ..world import OBJECT_SIZE as R

__all__ = ["SETTINGS", "sample", "test_pair", "training"]

SETTINGS = ("S1", "S2")
_CUBES, _WALL = (0, 1, 2), 3


def _spread(rng: np.random.Generator, low: float, high: float, gap: float) -> list[float]:
    """Three values in [low, high], sorted, at least `gap` apart (rejection sampling)."""
    while True:
        values = np.sort(rng.uniform(low, high, size=3))
        if np.all(np.diff(values) >= gap):
            return [float(v) for v in values]


def sample(rng: np.random.Generator) -> Scene:
    """Three dropped cubes, staggered in height so that they land one after another."""
    wall_x = rng.uniform(30.0, 34.0)
    half_width = rng.uniform(17.0, 20.0)
    height = rng.uniform(14.0, 22.0)
    xs = _spread(rng, wall_x - half_width + R + 1, wall_x + half_width - R - 1, 2 * R + 2)
    drop_heights = rng.permutation(_spread(rng, 78.0, 110.0, 6.0))
    things = [cube(x, y=float(y)) for x, y in zip(xs, drop_heights)]
    return make_scene(rng, things + [wall(wall_x, half_width, height)])


def _rest_on_floor(scene: Scene, index: int) -> Scene:
    things = list(scene.things)
    things[index] = replace(things[index], y=FLOOR + R)
    return replace(scene, things=tuple(things))


def _landing_frame(take: Take, index: int) -> int:
    """The first frame at which a cube rests on the floor."""
    resting = take.trajectory.position[:, index, 1] <= FLOOR + R + 0.05
    return int(np.argmax(resting)) if resting.any() else -1


def test_pair(rng: np.random.Generator, setting: str, frames: int) -> tuple[Take, Take]:
    scene = sample(rng)
    if setting == "S1":
        scene = scene.with_schedule("away_start_end")
        expected = run(scene, frames)
        first = min(_CUBES, key=lambda i: _landing_frame(expected, i))
        event = _landing_frame(expected, first) + 1
        expected.event_frame = event
        other = run(scene.with_edits(Edit(event, "remove", first)), frames, possible=False, event_frame=event)
        return expected, other
    if setting == "S2":
        scene = scene.with_schedule("away_end")
        resting = int(rng.integers(3))
        return run(scene, frames), run(_rest_on_floor(scene, resting), frames)
    raise ValueError(f"permanence has no setting {setting!r}")


def training(rng: np.random.Generator, with_wall: bool, frames: int) -> Take:
    scene = sample(rng).with_schedule("away_start_end")
    for index in _CUBES:
        if rng.random() < 0.5:
            scene = _rest_on_floor(scene, index)
    return run(scene if with_wall else scene.without(_WALL), frames)
