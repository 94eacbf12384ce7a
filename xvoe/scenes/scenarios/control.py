"""Control (training only): a ball rolls across the floor and meets nothing."""
from __future__ import annotations

import numpy as np

from ..physics import Take, run
from ..world import ball, make_scene, rolling_speed, wall

__all__ = ["training"]

_WALL = 1


def training(rng: np.random.Generator, with_wall: bool, frames: int) -> Take:
    things = [ball(rng.uniform(0.0, 20.0), rolling_speed(rng)),
              wall(rng.uniform(16.0, 48.0), rng.uniform(8.0, 16.0), rng.uniform(14.0, 26.0))]
    scene = make_scene(rng, things, wall_schedule="away_start_end")
    return run(scene if with_wall else scene.without(_WALL), frames)
