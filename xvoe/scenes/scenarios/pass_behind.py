"""Pass-behind (training only): a ball rolls behind the wall and nothing is there."""
from __future__ import annotations

import numpy as np

from ..physics import Take
from . import behind

__all__ = ["training"]


def training(rng: np.random.Generator, with_wall: bool, frames: int) -> Take:
    return behind.training(rng, with_wall, frames, make_hidden=None)
