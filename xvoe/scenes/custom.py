"""Make your own VoE event: place objects by hand, choose a violation, simulate, render, save.

    from xvoe import custom
    pair = custom.make_pair(
        [custom.ball(4, vx=50), custom.ball(34), custom.wall(32, half_width=12, height=18)],
        custom.pass_through(0, 1),      # the incoming ball goes through the one behind the wall
        wall="S3")                      # the wall's timetable: S1, S2, S3 (or its name)
    path = pair.save("my-event.h5", size=32)

The file is a test split of one pair (member 0 the expected video, member 1 the edited,
impossible one), in the schema every other part of xvoe reads: `xvoe score`, `xvoe explain`,
`xvoe show` and `xvoe.plot_surprise_curves` take it as they take a generated test set.

Places are in world units: the camera sees x in [0, 64] (left to right) and y in [0, 64]
(up); the floor's top is at y = 12 and balls and cubes have radius (half side) 4, so an
object resting on the floor has y = 16 (the default). Speeds are world units per second; a
video lasts 1.5 s whatever its frame count. A wall of height h stands on the floor and hides
what is behind it, from x - half_width to x + half_width and up to y = 12 + h.

The violation is an edit of the simulation, made the way the benchmark makes its impossible
videos: the same scene re-run and edited in the step into the event frame, so the two
members are identical before it.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import XvoeError
from . import world
from .physics import Take, run
from .render import Video, render
from .world import Edit, Scene, Thing, ball, cube, wall
from .writer import Writer, atomic_file, encode, write_attributes

__all__ = ["ball", "cube", "wall", "Violation", "pass_through", "remove", "teleport", "CustomPair", "make_pair",
           "save_pairs", "SETTING_OF_SCHEDULE"]

# The wall's timetable names the setting the pair is labelled with (permanence S2 aside, the
# benchmark's settings use these timetables).
SETTING_OF_SCHEDULE = {"away_start_end": "S1", "stays": "S2", "away_end": "S3"}
_SCHEDULE_OF_SETTING = {setting: schedule for schedule, setting in SETTING_OF_SCHEDULE.items()}
_ACTIONS = ("pass_through", "remove", "teleport")


@dataclass(frozen=True)
class Violation:
    """What makes member 1 impossible: an edit of thing `a` (and `b`) at `frame`.

    `frame` None (pass-through only) means the first contact of a and b in the expected video.
    """

    action: str
    a: int
    b: int = -1
    frame: int | None = None
    dx: float = 0.0


def pass_through(a: int, b: int) -> Violation:
    """Things a and b pass through each other instead of colliding (at their first contact)."""
    return Violation("pass_through", a, b)


def remove(a: int, frame: int) -> Violation:
    """Thing a vanishes at `frame`."""
    return Violation("remove", a, frame=frame)


def teleport(a: int, frame: int, dx: float) -> Violation:
    """Thing a jumps by dx world units (to the right) at `frame`; moved into another thing, it
    collides with it."""
    return Violation("teleport", a, frame=frame, dx=dx)


@dataclass
class CustomPair:
    """Two simulated videos of one hand-made scene: member 0 expected, member 1 edited."""

    expected: Take
    impossible: Take
    setting: str
    name: str = "custom"

    @property
    def takes(self) -> tuple[Take, Take]:
        return self.expected, self.impossible

    @property
    def event_frame(self) -> int:
        return self.impossible.event_frame

    def render(self, size: int = 64) -> list[Video]:
        """Both members drawn at size x size: the arrays the HDF5 file stores."""
        _check_size(size)
        return [render(take.scene, take.trajectory, size) for take in self.takes]

    def save(self, out: str | Path, size: int = 64, overwrite: bool = False) -> Path:
        """Write the pair as a test split file (pair 0); returns its path."""
        return save_pairs([self], out, size=size, overwrite=overwrite)


def make_pair(things: list[Thing], violation: Violation, *, wall: str = "S3", frames: int = 15, seed: int = 0,
              name: str = "custom") -> CustomPair:
    """Simulate the scene as placed (member 0) and again with the violation (member 1).

    things: balls, cubes and walls made with `ball`, `cube` and `wall` (at most 8); a thing
    keeps its colour if it has one, the others (and the background and floor) get distinct
    random colours from `seed`. wall: the wall's timetable, as a setting (S1: away at the start
    and the end, S2: stays, S3: away at the end) or by name (away_start_end, stays, away_end);
    it also names the pair's setting label, with or without a wall in the scene.
    """
    schedule, setting = _schedule(wall)
    if not 10 <= frames <= 200:
        raise XvoeError(f"frames must be between 10 and 200, not {frames}")
    things = _check_things(things)
    _check_violation(things, violation, frames)
    rng = np.random.default_rng(seed)
    colors = world.sample_colors(rng, 2 + len(things))
    things = [t if t.color != world.NO_COLOR else replace(t, color=c) for t, c in zip(things, colors[2:])]
    slots = tuple(int(s) for s in rng.permutation(world.MAX_SLOTS)[: len(things)])
    scene = Scene(tuple(things), colors[0], colors[1], schedule, False, slots)

    expected = run(scene, frames)
    event = violation.frame
    if violation.action == "pass_through":
        event = expected.trajectory.first_contact(violation.a, violation.b)
        if event < 0:
            raise XvoeError(f"things {violation.a} and {violation.b} never touch in the expected video, so there is "
                            "nothing to pass through: put them on a collision course (a ball rolling into a ball "
                            "or a fixed cube) within the video's 1.5 s")
    edit = Edit(event, violation.action, violation.a, violation.b, violation.dx)
    expected.event_frame = event
    impossible = run(scene.with_edits(edit), frames, possible=False, event_frame=event)
    return CustomPair(expected, impossible, setting, name)


def save_pairs(pairs: list[CustomPair], out: str | Path, *, size: int = 64, overwrite: bool = False) -> Path:
    """Write pairs (pair index = position in the list) as one test split file."""
    if not pairs:
        raise XvoeError("save_pairs needs at least one pair")
    _check_size(size)
    frames = {len(take.trajectory.position) for pair in pairs for take in pair.takes}
    if len(frames) != 1:
        raise XvoeError(f"all pairs of a file must have the same frame count, not {sorted(frames)}")
    config = {"custom": True, "size": size, "frames": frames.pop(), "pairs": len(pairs),
              "scenes": [[asdict(thing) for thing in pair.expected.scene.things] for pair in pairs],
              "violations": [asdict(pair.impossible.scene.edits[-1]) for pair in pairs]}
    with atomic_file(out, overwrite) as file:
        write_attributes(file, "test", config, seed=0)
        writer = Writer(file, "test", 2 * len(pairs), config["frames"], size)
        for index, pair in enumerate(pairs):
            for member, (take, video) in enumerate(zip(pair.takes, pair.render(size))):
                writer.add(encode(video, {"scenario": pair.name, "setting": pair.setting, "pair": index,
                                                "member": member, "possible": take.possible,
                                                "event_frame": take.event_frame}))
        writer.finish()
    return Path(out)


# --- checks ------------------------------------------------------------------------------

def _schedule(wall: str) -> tuple[str, str]:
    if wall in _SCHEDULE_OF_SETTING:
        return _SCHEDULE_OF_SETTING[wall], wall
    if wall in SETTING_OF_SCHEDULE:
        return wall, SETTING_OF_SCHEDULE[wall]
    raise XvoeError(f"wall must be a setting ({', '.join(_SCHEDULE_OF_SETTING)}) or a timetable "
                    f"({', '.join(world.WALL_SCHEDULES)}), not {wall!r}")


def _check_size(size: int) -> None:
    if not 16 <= size <= 512:
        raise XvoeError(f"size must be between 16 and 512 pixels, not {size}")


def _check_things(things) -> list[Thing]:
    things = list(things)
    if not 1 <= len(things) <= world.MAX_SLOTS:
        raise XvoeError(f"a scene holds 1 to {world.MAX_SLOTS} things, not {len(things)}")
    for i, thing in enumerate(things):
        if not isinstance(thing, Thing):
            raise XvoeError(f"thing {i} is a {type(thing).__name__}; make things with custom.ball, custom.cube "
                            "or custom.wall")
        if thing.kind not in world.KIND_NAMES[1:]:
            raise XvoeError(f"thing {i} has an unknown kind {thing.kind!r}")
        if thing.kind in world.WALL_KINDS:
            if thing.half_width <= 0 or thing.height <= 0:
                raise XvoeError(f"wall {i} needs a positive half_width and height")
            continue
        if not -world.WORLD <= thing.x <= 2 * world.WORLD:
            raise XvoeError(f"thing {i} starts at x = {thing.x:g}, far outside the view (x from 0 to {world.WORLD:g})")
        if thing.y < world.FLOOR + thing.size - 1e-6:
            raise XvoeError(f"thing {i} starts at y = {thing.y:g}, below the floor: the lowest place for it is "
                            f"y = {world.FLOOR + thing.size:g}")
    solid = [(i, t) for i, t in enumerate(things) if t.kind not in world.WALL_KINDS]
    for n, (i, a) in enumerate(solid):
        for j, b in solid[n + 1:]:
            if abs(a.x - b.x) < a.size + b.size - 1e-6 and abs(a.y - b.y) < a.size + b.size - 1e-6:
                raise XvoeError(f"things {i} and {j} overlap at the start (x = {a.x:g} and {b.x:g}); "
                                f"place them at least {a.size + b.size:g} apart")
    return things


def _check_violation(things: list[Thing], violation: Violation, frames: int) -> None:
    if not isinstance(violation, Violation):
        raise XvoeError("the violation must be custom.pass_through(a, b), custom.remove(a, frame) or "
                        "custom.teleport(a, frame, dx)")
    if violation.action not in _ACTIONS:
        raise XvoeError(f"unknown violation {violation.action!r}; expected one of {', '.join(_ACTIONS)}")
    involved = [violation.a] + ([violation.b] if violation.action == "pass_through" else [])
    for index in involved:
        if not 0 <= index < len(things):
            raise XvoeError(f"the violation names thing {index}, but the scene has things 0..{len(things) - 1}")
        if things[index].kind in world.WALL_KINDS:
            raise XvoeError(f"thing {index} is a wall; walls are not simulated, so a violation must name a ball "
                            "or a cube")
    if violation.action == "pass_through":
        if violation.a == violation.b:
            raise XvoeError("pass_through needs two different things")
        return
    if violation.frame is None or not 1 <= violation.frame <= frames - 1:
        raise XvoeError(f"the violation's frame must be between 1 and {frames - 1}, not {violation.frame}")
