"""Runs a scene in pymunk 7 and records every thing's state at every frame.

Balls roll (their angular velocity matches their speed, and floor friction keeps it so).
Contacts that the benchmark is about are resolved exactly rather than by the iterative
solver: two balls of equal mass exchange linear and angular velocity (the incoming ball
stops, the hit one rolls on, as in Newton's cradle), and a fixed cube sends a ball back with
its velocity and spin reversed. Walls are not simulated at all: they stand in a nearer depth
lane and follow their timetable, so they cannot touch anything.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymunk

from .world import DURATION, FLOOR, GRAVITY, WALL_KINDS, Scene

__all__ = ["SUBSTEPS", "Take", "Trajectory", "run", "simulate"]

BALL, CUBE, GROUND = 1, 2, 3
SUBSTEPS = 20


@dataclass
class Trajectory:
    """World-unit states (y up) of each thing at each frame."""

    position: np.ndarray    # (T, n, 2)
    velocity: np.ndarray    # (T, n, 2) world units per second
    angle: np.ndarray       # (T, n) radians
    present: np.ndarray     # (T, n) bool
    contacts: list[tuple[int, int, int]]   # (frame, a, b): exact contacts, in order

    def first_contact(self, a: int, b: int) -> int:
        """The first frame reached after things a and b touched, or -1."""
        for frame, i, j in self.contacts:
            if {i, j} == {a, b}:
                return frame
        return -1


def simulate(scene: Scene, frames: int, substeps: int = SUBSTEPS) -> Trajectory:
    """Simulate `scene` for `frames` frames spread over DURATION seconds."""
    space = _space()
    bodies, shapes = _add_things(space, scene)
    contacts = _Contacts(bodies, shapes)
    space.on_collision(BALL, BALL, begin=contacts.balls_meet)
    space.on_collision(BALL, CUBE, begin=contacts.ball_meets_cube)
    space.on_collision(CUBE, GROUND, begin=contacts.cube_lands)

    n = len(scene.things)
    position = np.zeros((frames, n, 2))     # (T, n, 2)
    velocity = np.zeros((frames, n, 2))     # (T, n, 2)
    angle = np.zeros((frames, n))           # (T, n)
    present = np.zeros((frames, n), dtype=bool)
    for i, thing in enumerate(scene.things):     # walls and absent things keep their spec
        position[:, i] = (thing.x, thing.y)
        present[:, i] = thing.exists and thing.kind in WALL_KINDS
    edits = sorted(scene.edits, key=lambda e: e.frame)
    dt = DURATION / frames / substeps

    for frame in range(frames):
        if frame > 0:
            contacts.frame = frame
            for edit in edits:
                if edit.frame == frame:
                    _apply(edit, space, bodies, shapes, contacts.ghosts)
            for _ in range(substeps):
                space.step(dt)
        for i, body in bodies.items():
            if body.space is None:
                continue
            position[frame, i] = body.position
            velocity[frame, i] = body.velocity
            angle[frame, i] = body.angle
            present[frame, i] = True
    return Trajectory(position, velocity, angle, present, contacts.found)


def _space() -> pymunk.Space:
    """An empty world with gravity and the floor."""
    space = pymunk.Space()
    space.gravity = (0.0, -GRAVITY)
    space.collision_slop = 0.01             # resting contacts sink by at most this much
    floor = pymunk.Segment(space.static_body, (-1e4, FLOOR - 1.0), (1e4, FLOOR - 1.0), 1.0)
    floor.friction = 1.0
    floor.elasticity = 0.0
    floor.collision_type = GROUND
    space.add(floor)
    return space


def _add_things(space: pymunk.Space, scene: Scene) -> tuple[dict[int, pymunk.Body], dict[int, pymunk.Shape]]:
    """The bodies and shapes of the scene's things that exist, by index; walls are never simulated."""
    bodies: dict[int, pymunk.Body] = {}
    shapes: dict[int, pymunk.Shape] = {}
    for i, thing in enumerate(scene.things):
        if thing.kind in WALL_KINDS or not thing.exists:
            continue
        body, shape = _make_body(thing)
        space.add(body, shape)
        bodies[i], shapes[i] = body, shape
    return bodies, shapes


class _Contacts:
    """The contacts resolved exactly rather than by the solver, and the list of them by frame;
    `ghosts` holds the pairs an edit lets pass through each other."""

    def __init__(self, bodies: dict[int, pymunk.Body], shapes: dict[int, pymunk.Shape]):
        self.bodies, self.shapes = bodies, shapes
        self.owner = {id(body): i for i, body in bodies.items()}
        self.ghosts: set[frozenset[int]] = set()
        self.found: list[tuple[int, int, int]] = []     # (frame, a, b)
        self.frame = 0

    def _pair(self, arbiter: pymunk.Arbiter) -> tuple[int, int]:
        a, b = arbiter.bodies
        return self.owner[id(a)], self.owner[id(b)]

    def balls_meet(self, arbiter: pymunk.Arbiter, _space: pymunk.Space, _data) -> None:
        arbiter.process_collision = False
        i, j = self._pair(arbiter)
        if frozenset((i, j)) in self.ghosts:
            return
        a, b = self.bodies[i], self.bodies[j]
        a.velocity, b.velocity = b.velocity, a.velocity
        a.angular_velocity, b.angular_velocity = b.angular_velocity, a.angular_velocity
        self.found.append((self.frame, i, j))

    def ball_meets_cube(self, arbiter: pymunk.Arbiter, _space: pymunk.Space, _data) -> None:
        i, j = self._pair(arbiter)
        if frozenset((i, j)) in self.ghosts:
            arbiter.process_collision = False
            return
        ball_index = i if self.shapes[i].collision_type == BALL else j
        cube_index = j if ball_index == i else i
        if self.bodies[cube_index].body_type != pymunk.Body.STATIC:
            return          # a loose cube: let the solver handle it
        arbiter.process_collision = False
        ball = self.bodies[ball_index]
        ball.velocity = (-ball.velocity.x, ball.velocity.y)
        ball.angular_velocity = -ball.angular_velocity
        self.found.append((self.frame, ball_index, cube_index))

    def cube_lands(self, arbiter: pymunk.Arbiter, _space: pymunk.Space, _data) -> None:
        """A falling cube stops dead on the floor instead of sinking into it for a frame."""
        body = next(b for b in arbiter.bodies if b.body_type == pymunk.Body.DYNAMIC)
        half = self.shapes[self.owner[id(body)]].bb.top - body.position.y
        body.position = (body.position.x, FLOOR + half)
        body.velocity = (body.velocity.x, 0.0)


def _make_body(thing) -> tuple[pymunk.Body, pymunk.Shape]:
    if thing.kind == "ball":
        body = pymunk.Body(1.0, pymunk.moment_for_circle(1.0, 0.0, thing.size))
        shape = pymunk.Circle(body, thing.size)
        shape.collision_type = BALL
        body.angular_velocity = -thing.vx / thing.size     # rolling without slipping
    elif thing.kind == "cube":
        if thing.fixed:
            body = pymunk.Body(body_type=pymunk.Body.STATIC)
        else:
            body = pymunk.Body(1.0, float("inf"))           # cubes never tip over
        side = 2 * thing.size
        shape = pymunk.Poly.create_box(body, (side, side))
        shape.collision_type = CUBE
    else:
        raise ValueError(f"cannot simulate a thing of kind {thing.kind!r}")
    body.position = (thing.x, thing.y)
    if body.body_type != pymunk.Body.STATIC:
        body.velocity = (thing.vx, thing.vy)
    shape.friction = 1.0
    shape.elasticity = 0.0
    return body, shape


def _apply(edit, space: pymunk.Space, bodies, shapes, ghosts: set) -> None:
    if edit.action == "pass_through":
        ghosts.add(frozenset((edit.a, edit.b)))
    elif edit.action == "remove":
        space.remove(bodies[edit.a], shapes[edit.a])
    elif edit.action == "teleport":
        body = bodies[edit.a]
        body.position = (body.position.x + edit.dx, body.position.y)
    else:
        raise ValueError(f"unknown edit {edit.action!r}")


@dataclass
class Take:
    """One simulated video: the scene, its trajectory, its label and its event frame."""

    scene: Scene
    trajectory: Trajectory
    possible: bool = True
    event_frame: int = -1


def run(scene: Scene, frames: int, possible: bool = True, event_frame: int = -1) -> Take:
    return Take(scene, simulate(scene, frames), possible, event_frame)
