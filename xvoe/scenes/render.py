"""Draws a simulated scene into RGB, depth and slot-id frames with numpy alone.

The camera looks along the depth axis; each pixel keeps the nearest surface (a z-buffer).
Depth is the distance to the camera, in world units, stored as uint8 with DEPTH_FAR at 255:
walls stand at WALL_DEPTH, balls and cubes in a lane behind them (balls shaded as spheres),
the floor recedes from near at the bottom of the picture to the background at its top.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .physics import Trajectory
from .world import DURATION, FLOOR, KIND_NAMES, MAX_SLOTS, WALL_KINDS, WORLD, Scene, wall_fraction

__all__ = ["WALL_DEPTH", "OBJECT_DEPTH", "DEPTH_FAR", "STATE_COLUMNS", "Video", "render"]

WALL_DEPTH = 20.0
OBJECT_DEPTH = 40.0
_FLOOR_NEAR_DEPTH = 30.0
DEPTH_FAR = 80.0

STATE_COLUMNS = ("x", "y", "size", "height", "lane", "present", "visible", "vx", "vy", "angle")


@dataclass
class Video:
    """One rendered video in the storage layout (see xvoe.scenes.store)."""

    rgbd: np.ndarray     # (T, H, W, 4) uint8
    ids: np.ndarray      # (T, H, W) uint8: 0 background, k+1 slot k
    states: np.ndarray   # (T, K, S) float32, columns STATE_COLUMNS, pixel units, y down
    kind: np.ndarray     # (K,) int8 index into KIND_NAMES
    color: np.ndarray    # (K, 3) uint8


def render(scene: Scene, trajectory: Trajectory, size: int = 64) -> Video:
    """Rasterise every frame of a simulated scene at `size` x `size` pixels."""
    frames = trajectory.position.shape[0]
    scale = size / WORLD
    centers = (np.arange(size) + 0.5) / scale       # pixel centres in world units
    xs, ys_down = centers, centers                   # x to the right; image rows downwards
    floor_rows = (WORLD - ys_down) < FLOOR
    floor_depth = _floor_depth(ys_down)

    rgb = np.empty((frames, size, size, 3), np.uint8)
    depth = np.empty((frames, size, size), np.float32)
    ids = np.zeros((frames, size, size), np.uint8)
    rgb[:] = scene.background
    rgb[:, floor_rows] = scene.floor
    depth[:] = DEPTH_FAR
    depth[:, floor_rows] = floor_depth[floor_rows, None]

    states = np.zeros((frames, MAX_SLOTS, len(STATE_COLUMNS)), np.float32)
    kind = np.zeros(MAX_SLOTS, np.int8)
    color = np.zeros((MAX_SLOTS, 3), np.uint8)
    silhouette_area = np.zeros((frames, MAX_SLOTS))
    sign = -1.0 if scene.mirror else 1.0

    for index, (thing, slot) in enumerate(zip(scene.things, scene.slots)):
        if not thing.exists:
            continue
        kind[slot] = KIND_NAMES.index(thing.kind)
        color[slot] = thing.color
        for t in range(frames):
            if not trajectory.present[t, index]:
                continue
            x, y = trajectory.position[t, index]
            if thing.kind in WALL_KINDS:
                fraction = wall_fraction(scene.wall_schedule, t * DURATION / frames)
                y = thing.y + (1.0 - fraction) * (WORLD - FLOOR)
            if scene.mirror:
                x = WORLD - x
            area = _draw(thing, x, y, xs, ys_down, rgb[t], depth[t], ids[t], slot + 1)
            silhouette_area[t, slot] = area
            vx, vy = trajectory.velocity[t, index] * (DURATION / frames) * scale
            row = states[t, slot]
            row[:] = (x * scale, (WORLD - y) * scale,
                      (thing.half_width if thing.kind in WALL_KINDS else thing.size) * scale,
                      (thing.height if thing.kind in WALL_KINDS else 2 * thing.size) * scale,
                      thing.lane, 1.0, 0.0, sign * vx, -vy, sign * trajectory.angle[t, index])

    labels = ids.reshape(frames, -1).astype(np.int64) + (MAX_SLOTS + 1) * np.arange(frames)[:, None]
    pixel_counts = np.bincount(labels.ravel(), minlength=frames * (MAX_SLOTS + 1)).reshape(frames, -1)
    visible = pixel_counts[:, 1:] / np.maximum(silhouette_area, 1)
    states[..., STATE_COLUMNS.index("visible")] = visible
    depth_u8 = np.clip(np.rint(depth * (255.0 / DEPTH_FAR)), 0, 255).astype(np.uint8)
    rgbd = np.concatenate([rgb, depth_u8[..., None]], axis=-1)
    return Video(rgbd, ids, states, kind, color)


def _floor_depth(ys_down: np.ndarray) -> np.ndarray:
    """Depth of the floor seen at each image row: near at the bottom, far at its top edge."""
    height_in_floor = np.clip((WORLD - ys_down) / FLOOR, 0.0, 1.0)
    return _FLOOR_NEAR_DEPTH + height_in_floor * (DEPTH_FAR - _FLOOR_NEAR_DEPTH)


def _draw(thing, x: float, y: float, xs: np.ndarray, ys_down: np.ndarray, rgb: np.ndarray,
          depth: np.ndarray, ids: np.ndarray, label: int) -> int:
    """Z-buffer one thing into a frame; returns the pixel count of its whole silhouette."""
    y_down = WORLD - y
    if thing.kind in WALL_KINDS:
        half_w, half_h = thing.half_width, thing.height / 2
    else:
        half_w = half_h = thing.size
    cols = _span(xs, x - half_w, x + half_w)
    rows = _span(ys_down, y_down - half_h, y_down + half_h)
    if cols.start >= cols.stop or rows.start >= rows.stop:
        return 0
    dx = xs[cols][None, :] - x
    dy = ys_down[rows][:, None] - y_down
    if thing.kind == "ball":
        d2 = dx * dx + dy * dy
        mask = d2 <= thing.size ** 2
        z = OBJECT_DEPTH - np.sqrt(np.maximum(thing.size ** 2 - d2, 0.0))
    elif thing.kind == "cube":
        mask = (np.abs(dx) <= thing.size) & (np.abs(dy) <= thing.size)
        z = np.full(mask.shape, OBJECT_DEPTH - thing.size)
    else:
        mask = (np.abs(dx) <= half_w) & (np.abs(dy) <= half_h)
        if thing.window is not None:
            win_w, win_h = thing.window
            bottom = half_h                              # dy is measured downwards
            hole = (np.abs(dx) <= win_w) & (dy >= bottom - win_h)
            mask &= ~hole
        z = np.full(mask.shape, WALL_DEPTH)
    region = depth[rows, cols]
    wins = mask & (z < region)
    region[wins] = z[wins]
    rgb[rows, cols][wins] = thing.color
    ids[rows, cols][wins] = label
    return int(mask.sum())


def _span(centers: np.ndarray, low: float, high: float) -> slice:
    """Index range of the pixel centres inside [low, high] (centres are (i + 0.5) / scale)."""
    scale = len(centers) / WORLD
    first = max(0, math.ceil(low * scale - 0.5))
    last = min(len(centers) - 1, math.floor(high * scale - 0.5))
    return slice(first, max(first, last + 1))


