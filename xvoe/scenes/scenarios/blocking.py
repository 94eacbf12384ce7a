"""Blocking: a ball rolls behind a wall where a fixed cube stands, and bounces back.

Member 0: the ball returns. Member 1: S1 and S3, the ball passes through the cube
(impossible); S2, nothing stands behind the wall and the ball rolls on (possible).
"""
from __future__ import annotations

import numpy as np

from ..physics import Take
from ..world import Scene, cube
from . import behind

__all__ = ["SETTINGS", "sample", "test_pair", "training"]

SETTINGS = ("S1", "S2", "S3")


def _fixed_cube(x: float):
    return cube(x, fixed=True)


def sample(rng: np.random.Generator) -> Scene:
    return behind.sample(rng, _fixed_cube)


def test_pair(rng: np.random.Generator, setting: str, frames: int) -> tuple[Take, Take]:
    return behind.test_pair(rng, setting, frames, make_hidden=_fixed_cube)


def training(rng: np.random.Generator, with_wall: bool, frames: int) -> Take:
    return behind.training(rng, with_wall, frames, make_hidden=_fixed_cube)
