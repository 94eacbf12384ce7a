"""Collision: a ball rolls behind a wall where a second ball of the same mass waits.

Member 0: the incoming ball stops and the hit ball rolls on (Newton's cradle). Member 1:
S1 and S3, the incoming ball passes through the hidden one (impossible); S2, nothing waits
behind the wall and the incoming ball rolls on (possible).
"""
from __future__ import annotations

import numpy as np

from ..physics import Take
from ..world import Scene, ball
from . import behind

__all__ = ["SETTINGS", "sample", "test_pair", "training"]

SETTINGS = ("S1", "S2", "S3")


def sample(rng: np.random.Generator) -> Scene:
    return behind.sample(rng, ball)


def test_pair(rng: np.random.Generator, setting: str, frames: int) -> tuple[Take, Take]:
    return behind.test_pair(rng, setting, frames, make_hidden=ball)


def training(rng: np.random.Generator, with_wall: bool, frames: int) -> Take:
    return behind.training(rng, with_wall, frames, make_hidden=ball)
