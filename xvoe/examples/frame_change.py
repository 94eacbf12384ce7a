"""A pixel model: a frame is as surprising as it is different from the one before.

It knows nothing of objects or walls, so it is surprised by every motion alike. On the
benchmark it shows what pixel change alone separates: the pairs whose impossible member moves
more, or differently, in plain view.

    xvoe score --model xvoe.examples.frame_change:FrameChange --data test.h5 --out change.csv
"""
import numpy as np

import xvoe

__all__ = ["FrameChange"]


class FrameChange:
    name = "frame-change"
    curve = "frame_change"              # its per-frame surprise, stored under this name and drawn on this axis
    curve_label = "summed squared change of the frame"

    def surprise(self, videos: xvoe.Videos) -> np.ndarray:
        """Per frame, the summed squared change of RGB and depth from the frame before (0 at the first)."""
        frames = videos.rgbd.astype(np.float32) / 255.0
        change = np.zeros(frames.shape[:2])
        change[:, 1:] = ((frames[:, 1:] - frames[:, :-1]) ** 2).sum(axis=(2, 3, 4))
        return change
