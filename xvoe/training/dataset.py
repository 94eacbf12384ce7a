"""A split as a PyTorch dataset: one video per item, for a model of your own to train on or
be evaluated with, in a DataLoader with as many workers as you like."""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import torch
from torch.utils.data import Dataset

from ..scenes import store

__all__ = ["SplitDataset"]


class SplitDataset(Dataset):
    """The videos of a split file: `rgbd` (T, H, W, 4) and `ids` (T, H, W) uint8 tensors, the
    per-slot `states` (T, K, S) and `kind` (K,), the labels of its split (test: scenario,
    setting, pair, member, possible, event_frame; train: group, has_wall, event_frame), and
    `index`. Every process opens the file for itself on first use: an h5py handle must not
    cross a fork into DataLoader workers."""

    def __init__(self, path: str | os.PathLike):
        self.path = str(Path(path))
        with store.open_dataset(self.path) as file:
            self.split = str(file.attrs["split"])
            self.count = int(file["rgbd"].shape[0])
            self.state_columns = list(file["states"].attrs["state_columns"])
            self.kind_names = list(file.attrs["kind_names"])
        self.labels = store.TEST_LABELS if self.split == "test" else store.TRAIN_LABELS
        self._file: h5py.File | None = None
        self._owner: int | None = None

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int) -> dict:
        if not -self.count <= index < self.count:
            raise IndexError(f"video {index} of a split of {self.count}")
        index %= self.count
        file = self._open()
        item = {"index": index, "rgbd": torch.from_numpy(store.read_frames(file, "rgbd", index)),
                "ids": torch.from_numpy(store.read_frames(file, "ids", index)),
                "states": torch.from_numpy(store.read_states(file, index)),
                "kind": torch.from_numpy(file["kind"][index])}
        for name in self.labels:
            value = file[name][index]
            item[name] = value.decode() if isinstance(value, bytes) else value.item()
        return item

    def _open(self) -> h5py.File:
        if self._file is None or self._owner != os.getpid():
            self._file, self._owner = store.open_dataset(self.path), os.getpid()
        return self._file

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_file": None, "_owner": None}
