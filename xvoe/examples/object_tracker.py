"""An object model from the slot masks: it follows each object and is surprised when one
appears, vanishes or jumps where no wall could explain it.

It reads the `ids` masks (which slot each pixel shows), so it sees objects perfectly but has
no physics: it cannot tell a ball that should have stopped from one that did. Walls are the
nearest slots (dark in the depth channel); an object leaving view behind a wall is
remembered, and missed if the wall goes and it is not there.

    xvoe score --model xvoe.examples.object_tracker:ObjectTracker --data test.h5 --out tracker.csv
"""
import numpy as np

import xvoe

__all__ = ["WALL_DEPTH", "ObjectTracker"]

JUMP = 6.0          # pixels a centroid may move in a frame at 64x64 (scaled by the frame size)
NEAR_WALL = 3       # pixels from a wall's box within which appearing or vanishing is expected
WALL_DEPTH = 96     # walls stand nearer the camera than objects: darker than this in the depth channel


class ObjectTracker:
    name = "object-tracker"
    curve = "events"
    curve_label = "unexplained appearances, disappearances and jumps"

    def surprise(self, videos: xvoe.Videos) -> np.ndarray:
        batch, frames, size = videos.ids.shape[:3]
        surprise = np.zeros((batch, frames))
        for b in range(batch):
            surprise[b] = self._one(videos.ids[b], videos.rgbd[b, ..., 3], size)
        return surprise

    def _one(self, ids: np.ndarray, depth: np.ndarray, size: int) -> np.ndarray:
        slots = [s for s in np.unique(ids) if s != 0]
        walls = [s for s in slots if np.median(depth[ids == s]) < WALL_DEPTH]
        objects = [s for s in slots if s not in walls]
        seen = {s: (ids == s).any(axis=(1, 2)) for s in objects}
        centre = {s: [np.argwhere(ids[t] == s).mean(axis=0) if seen[s][t] else None for t in range(len(ids))]
                  for s in objects}
        surprise = np.zeros(len(ids))
        remembered: dict[int, np.ndarray] = {}       # objects gone from view: where they were last seen
        jump = JUMP * size / 64
        for t in range(1, len(ids)):
            for slot in objects:
                now, before = seen[slot][t], seen[slot][t - 1]
                if before and not now:
                    place = centre[slot][t - 1]
                    if _near_walls(place, ids, t, walls):
                        remembered[slot] = place            # gone behind a wall
                    elif not _near_edge(place, size):
                        surprise[t] += 1.0                  # vanished in plain view
                elif now and not before:
                    known = remembered.pop(slot, None) is not None
                    if not known and not _near_edge(centre[slot][t], size) \
                            and not _near_walls(centre[slot][t], ids, t, walls):
                        surprise[t] += 1.0                  # appeared from nowhere
                elif now and np.abs(centre[slot][t] - centre[slot][t - 1]).max() > jump \
                        and not _near_walls(centre[slot][t], ids, t, walls):
                    surprise[t] += 1.0                      # teleported (a partly hidden one's centre moves)
            for slot, place in list(remembered.items()):   # the wall lifted: is the object still there?
                x = int(round(place[1]))
                columns = ids[t, :, max(0, x - NEAR_WALL):x + NEAR_WALL + 1]
                if not np.isin(columns, walls).any() and not seen[slot][t]:
                    surprise[t] += 1.0
                    del remembered[slot]
        return surprise


def _box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    found = np.argwhere(mask.any(axis=0))
    if not len(found):
        return None
    (top, left), (bottom, right) = found.min(axis=0), found.max(axis=0)
    return int(top), int(left), int(bottom), int(right)


def _near_edge(centre: np.ndarray, size: int) -> bool:
    return bool(np.any(centre < NEAR_WALL + 4) or np.any(centre > size - NEAR_WALL - 5))


def _near_walls(centre: np.ndarray, ids: np.ndarray, t: int, walls: list[int]) -> bool:
    for wall in walls:
        frame_box = _box(ids[max(0, t - 1):t + 1] == wall)
        if frame_box is None:
            continue
        top, left, bottom, right = frame_box
        if left - NEAR_WALL - 4 <= centre[1] <= right + NEAR_WALL + 4:
            return True
    return False
