"""What a scene is: the things in it, their colours, the wall's timetable and the edits.

Scenes are described in world units: the camera sees x in [0, WORLD] (left to right) and
y in [0, WORLD] (floor at the bottom, gravity down), whatever the rendered size. A scene is
plain data; `xvoe.scenes.physics.simulate` runs it and `xvoe.scenes.render.render` draws it.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["WORLD", "FLOOR", "DURATION", "OBJECT_SIZE", "GRAVITY", "KIND_NAMES", "WALL_KINDS", "MAX_SLOTS",
           "WALL_SCHEDULES", "wall_fraction", "Thing", "Edit", "Scene", "sample_colors", "make_scene",
           "NO_COLOR", "ball", "cube", "wall", "rolling_speed"]

WORLD = 64.0          # the camera's field of view, world units (= pixels at 64x64)
FLOOR = 12.0          # height of the floor's top surface
DURATION = 1.5        # seconds of simulated time in a video, whatever the frame count
OBJECT_SIZE = 4.0     # radius of a ball and half side of a cube
GRAVITY = 200.0       # world units per second squared

_OBJECT_LANE = 1       # balls and cubes move in this depth lane
_WALL_LANE = 0         # walls stand nearer the camera and never touch anything

KIND_NAMES = ("none", "ball", "cube", "wall", "window_wall")
WALL_KINDS = ("wall", "window_wall")
MAX_SLOTS = 8

# Wall timetables: fraction of the wall lowered into view (1 = standing on the floor,
# 0 = lifted out of the picture) as a function of time in seconds.
WALL_SCHEDULES = ("away_start_end", "stays", "away_end")
_MOVE = 0.2           # seconds a lift or a lowering takes
_LOWER_AT = 0.1       # lowering starts here in "away_start_end"
_LIFT_AT = DURATION - 0.2 - _MOVE   # the wall is gone at DURATION - 0.2


def wall_fraction(schedule: str, time: float) -> float:
    """How far the wall is lowered at `time` under a timetable."""
    lowered = float(np.clip(round((time - _LOWER_AT) / _MOVE, 9), 0.0, 1.0))
    not_lifted = float(np.clip(round((_LIFT_AT + _MOVE - time) / _MOVE, 9), 0.0, 1.0))
    if schedule == "away_start_end":
        return min(lowered, not_lifted)
    if schedule == "stays":
        return 1.0
    if schedule == "away_end":
        return not_lifted
    raise ValueError(f"unknown wall schedule {schedule!r}; expected one of {WALL_SCHEDULES}")


@dataclass(frozen=True)
class Thing:
    """One object of a scene, in world units (y up). Walls use `half_width` and `height`."""

    kind: str
    color: tuple[int, int, int]
    x: float
    y: float = FLOOR + OBJECT_SIZE
    vx: float = 0.0
    vy: float = 0.0
    size: float = OBJECT_SIZE
    fixed: bool = False           # a cube that nothing can move
    exists: bool = True           # False: the slot stays empty in this member of a pair
    half_width: float = 0.0       # walls only
    height: float = 0.0           # walls only
    window: tuple[float, float] | None = None   # window wall: (half width, height) of the hole

    @property
    def lane(self) -> int:
        return _WALL_LANE if self.kind in WALL_KINDS else _OBJECT_LANE


@dataclass(frozen=True)
class Edit:
    """A change to the simulation made just before the step into frame `frame`.

    `pass_through` lets things a and b pass through each other; `remove` takes thing a out;
    `teleport` moves thing a by dx. This is how impossible videos are made: the same scene
    re-run from the same seed, edited at the event frame.
    """

    frame: int
    action: str
    a: int
    b: int = -1
    dx: float = 0.0


@dataclass(frozen=True)
class Scene:
    things: tuple[Thing, ...]
    background: tuple[int, int, int]
    floor: tuple[int, int, int]
    wall_schedule: str = "stays"
    mirror: bool = False          # render right-to-left (the physics is symmetric)
    slots: tuple[int, ...] = ()   # slot index of each thing
    edits: tuple[Edit, ...] = field(default_factory=tuple)

    def with_edits(self, *edits: Edit) -> Scene:
        return replace(self, edits=self.edits + tuple(edits))

    def without(self, index: int) -> Scene:
        """The same scene with thing `index` absent (its slot stays empty)."""
        things = list(self.things)
        things[index] = replace(things[index], exists=False)
        return replace(self, things=tuple(things))

    def with_schedule(self, schedule: str) -> Scene:
        return replace(self, wall_schedule=schedule)


def sample_colors(rng: np.random.Generator, count: int, min_distance: float = 110.0) -> list[tuple[int, int, int]]:
    """`count` random colours, each at least `min_distance` (L1 over RGB) from the others."""
    colors: list[np.ndarray] = []
    while len(colors) < count:
        candidate = rng.integers(0, 256, size=3)
        if all(np.abs(candidate - c).sum() >= min_distance for c in colors):
            colors.append(candidate)
    return [tuple(int(v) for v in c) for c in colors]


def make_scene(rng: np.random.Generator, things: list[Thing], *, wall_schedule: str = "stays") -> Scene:
    """Colour the things, pick background and floor colours, the mirror flag and the slots.

    Things are passed with placeholder colours; every colour comes from one draw so that
    background, floor, walls and objects are all distinct.
    """
    colors = sample_colors(rng, 2 + len(things))
    background, floor = colors[0], colors[1]
    things = [replace(t, color=c) for t, c in zip(things, colors[2:])]
    mirror = bool(rng.integers(2))
    slots = tuple(int(s) for s in rng.permutation(MAX_SLOTS)[: len(things)])
    return Scene(tuple(things), background, floor, wall_schedule, mirror, slots)


NO_COLOR = (0, 0, 0)


def ball(x: float, vx: float = 0.0, y: float = FLOOR + OBJECT_SIZE) -> Thing:
    return Thing("ball", NO_COLOR, x=x, y=y, vx=vx)


def cube(x: float, y: float = FLOOR + OBJECT_SIZE, fixed: bool = False) -> Thing:
    return Thing("cube", NO_COLOR, x=x, y=y, fixed=fixed)


def wall(x: float, half_width: float, height: float, window: tuple[float, float] | None = None) -> Thing:
    kind = "window_wall" if window else "wall"
    return Thing(kind, NO_COLOR, x=x, y=FLOOR + height / 2, half_width=half_width, height=height, window=window)


def _frame_time(frame: float, frames: int) -> float:
    """Seconds at a (possibly fractional) frame index."""
    return frame * DURATION / frames


def rolling_speed(rng: np.random.Generator) -> float:
    """A ball speed in world units per second (about 5 pixels a frame at 15 frames, 64 px)."""
    return float(rng.uniform(44.0, 56.0))
