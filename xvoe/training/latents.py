"""The latent cache: a split encoded once by a trained perception module.

Later stages (reasoning, dynamics, scoring) read these posterior means and stds instead of
pixels. Schema (an interface; version in the attribute `xvoe_latents`):

- `mean`, `std` float32 (N, T, K, D): the posterior of each slot in each frame. Slots with no
  pixels hold the posterior of the blank input (the same for all of them).
- `visible` bool (N, T, K): the slot has more than `visible_threshold` mask pixels
  (4 at 128 px, scaled by area).
- `present` bool (N, T, K): the slot holds an object of the video in that frame (from states).
- extras: `pixels` int32 (N, T, K) mask pixel counts; `background_mean`, `background_std`
  float32 (N, T, D): the background component (floor and sky) that the composite needs.
- attributes: `perception_checkpoint` (path), `perception_sha256`, `source` (data file),
  `source_split`, `config` (JSON: recipe, perception config, threshold, the data's config), and
  the cache's key: `split_identity` (JSON, xvoe.fingerprints.split_identity) and `_perception_identity`
  (`encoder_key`: a hash of the module's weights and config, and the precision it encoded in
  where not float32). `check_cache` refuses a cache whose key is not the split's and the
  perception's at hand.

A test split's cache lies beside the split (`split_cache`, one per perception module): `xvoe
score` makes it on first use and every model that reads that perception reads it.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import torch

from ..errors import XvoeError
from ..fingerprints import arrays_hash, describe_split, split_identity
from ..models.config import to_dict
from ..models.devices import autocast_dtype, device_of, mixed_precision, resolve_device
from ..models.perception import ComponentVAE, normalise
from ..outputs import claim_file, claim_scope
from ..progress import progress_bar
from ..scenes import store
from ..scenes.writer import atomic_file
from .data import check_size, masked_inputs, visible_threshold
from .perception import load_perception
from .recipes import recipe_of
from .stages import PERCEPTION

__all__ = ["LATENT_CHUNK", "open_latents", "encode_frames", "encode_means", "encode_split", "encode_with",
           "encoder_key", "split_cache", "check_cache"]

_LATENTS_VERSION = 1
_ARRAYS = ("mean", "std", "visible", "present", "pixels", "background_mean", "background_std")


@dataclass
class _Latents:
    """A latent cache in memory."""

    mean: np.ndarray
    std: np.ndarray
    visible: np.ndarray
    present: np.ndarray
    pixels: np.ndarray
    background_mean: np.ndarray
    background_std: np.ndarray
    attrs: dict = field(default_factory=dict)

    @property
    def config(self) -> dict:
        return json.loads(self.attrs["config"])


def _sha256_of(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _write_latents(path: str | os.PathLike, latents: _Latents, overwrite: bool = False) -> Path:
    """Write a cache atomically (temporary name, then rename)."""
    with atomic_file(path, overwrite=overwrite) as file:
        for name in _ARRAYS:
            array = getattr(latents, name)
            file.create_dataset(name, data=array, track_times=False, **_compressed(array))
        file.attrs["xvoe_latents"] = _LATENTS_VERSION
        for name, value in latents.attrs.items():
            if name != "xvoe_latents":
                file.attrs[name] = value
    return Path(path)


LATENT_CHUNK = 16      # videos per compressed chunk and per encoder batch: a scoring batch reads one


def _compressed(array: np.ndarray) -> dict:
    """How a cache's array is stored: deflate at its fastest level over byte-shuffled chunks of
    videos, 9x smaller than the raw floats (the empty slots repeat one posterior) for 0.1 s more
    read per 10,000 videos (docs/decisions.md, "Speed and memory")."""
    if not len(array):
        return {}
    return {"chunks": (min(LATENT_CHUNK, len(array)), *array.shape[1:]), "compression": "gzip",
            "compression_opts": 1, "shuffle": True}


def open_latents(path: str | os.PathLike) -> h5py.File:
    """Open a latent cache for reading, or say in one line why it is not one."""
    file = store.open_hdf5(path)
    version = file.attrs.get("xvoe_latents")
    if version is None or int(version) != _LATENTS_VERSION:
        file.close()
        raise XvoeError(f"{path} is not an xvoe latent cache of version {_LATENTS_VERSION}")
    return file


def _read_latents(path: str | os.PathLike) -> _Latents:
    with open_latents(path) as file:
        arrays = {name: file[name][:] for name in _ARRAYS}
        attrs = {name: (value.item() if isinstance(value, np.generic) else value)
                 for name, value in file.attrs.items()}
    return _Latents(**arrays, attrs=attrs)


_ENCODE_CHUNK = 64   # images per encoder pass: the paper's ViT needs about 8 MiB of activations per image


@torch.no_grad()
def encode_frames(model, rgbd: np.ndarray, ids: np.ndarray, slots: int) -> dict[str, np.ndarray]:
    """Posteriors of every slot and of the background for frames (B,H,W,4), ids (B,H,W)."""
    device = model.theta.device
    frames = normalise(torch.as_tensor(rgbd)).to(device)
    parts = masked_inputs(frames, torch.as_tensor(ids).to(device), slots)
    count, objects = len(frames), len(parts["objects"])
    inputs = torch.cat([parts["objects"], parts["background"], model.blank()])
    with mixed_precision(device):
        posteriors = [model.posterior(part) for part in inputs.split(_ENCODE_CHUNK)]
    mean, std = (torch.cat(found).float() for found in zip(*posteriors))
    slot_mean = mean[-1:].expand(count, slots, -1).clone()
    slot_std = std[-1:].expand(count, slots, -1).clone()
    slot_mean[parts["object_frame"], parts["object_slot"]] = mean[:objects]
    slot_std[parts["object_frame"], parts["object_slot"]] = std[:objects]
    return {"mean": slot_mean.cpu().numpy(), "std": slot_std.cpu().numpy(),
            "background_mean": mean[objects:objects + count].cpu().numpy(),
            "background_std": std[objects:objects + count].cpu().numpy(),
            "pixels": parts["pixels"].cpu().numpy().astype(np.int32)}


def encode_means(model, rgbd: np.ndarray, ids: np.ndarray, slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Posterior means (V,T,K,D) and mask pixel counts (V,T,K) of every slot of videos (V,T,H,W,4)
    and their id maps (V,T,H,W), one video at a time (what the benchmarks probe)."""
    encoded = [encode_frames(model, rgbd[v], ids[v], slots) for v in range(len(rgbd))]
    return np.stack([e["mean"] for e in encoded]), np.stack([e["pixels"] for e in encoded])


def encode_split(model_ref: str | os.PathLike, data: str | os.PathLike, out: str | os.PathLike, *,
                 videos_per_batch: int = LATENT_CHUNK, overwrite: bool = False, progress: bool = True,
                 device: str | torch.device = "cpu") -> Path:
    """What `xvoe encode` does: encode every frame of a split into a latent cache, on `device`."""
    model, state = load_perception(model_ref, resolve_device(device))
    origin = {"perception_checkpoint": str(Path(state["path"]).resolve()),
              "perception_sha256": _sha256_of(state["path"]), "recipe": recipe_of(state["config"])}
    return encode_with(model, data, out, origin, videos_per_batch=videos_per_batch, overwrite=overwrite,
                       progress=progress)


@claim_scope()
def encode_with(model: ComponentVAE, data: str | os.PathLike, out: str | os.PathLike, origin: dict | None = None, *,
                videos_per_batch: int = LATENT_CHUNK, overwrite: bool = False, progress: bool = True,
                identity: dict | None = None) -> Path:
    """A split encoded by a loaded perception module into a latent cache, keyed by the split's
    identity and the module's (`check_cache`). `origin`: the checkpoint it was loaded from
    (`perception_checkpoint`, `perception_sha256`, `recipe`), where there is one; `identity`: the
    split's `split_identity`, where the caller has it (it hashes frames)."""
    origin = dict(origin or {})
    recipe_name = origin.pop("recipe", None)
    with store.open_dataset(data) as file:
        checkpoint = origin.get("perception_checkpoint")
        check_size(file, model.config.image_size, f"the checkpoint {checkpoint}" if checkpoint else "the perception")
        claim_file(out, overwrite)      # after every check of the input: a refused run leaves nothing behind
        count, frames, size = file["rgbd"].shape[:3]
        slots = int(file["states"].shape[2])
        present_column = list(file["states"].attrs["state_columns"]).index("present")
        # filled in place: small outputs kept in lists among each batch's large temporaries
        # fragment the heap (docs/decisions.md, "Speed and memory")
        arrays: dict[str, np.ndarray] = {}
        with progress_bar(total=count, desc="encode", disable=not progress, unit="video") as bar:
            for start in range(0, count, videos_per_batch):
                stop = min(count, start + videos_per_batch)
                rgbd, ids = store.read_frames(file, "rgbd", start, stop), store.read_frames(file, "ids", start, stop)
                encoded = encode_frames(model, rgbd.reshape(-1, size, size, 4), ids.reshape(-1, size, size), slots)
                for name, value in encoded.items():
                    if name not in arrays:
                        arrays[name] = np.empty((count, frames, *value.shape[1:]), value.dtype)
                    arrays[name][start:stop] = value.reshape(stop - start, frames, *value.shape[1:])
                bar.update(stop - start)
        present = file["states"][..., present_column] > 0.5
        threshold = visible_threshold(size)
        config = {"recipe": recipe_name, PERCEPTION: to_dict(model.config), "visible_threshold": threshold,
                  "data": store.config_of(file)}
        attrs = {**origin, "source": str(Path(data).resolve()), "source_split": str(file.attrs["split"]),
                 "config": json.dumps(config, sort_keys=True),
                 "split_identity": json.dumps(identity or split_identity(file), sort_keys=True),
                 "perception_identity": encoder_key(model)}
    latents = _Latents(visible=arrays["pixels"] > threshold, present=present, attrs=attrs, **arrays)
    return _write_latents(out, latents, overwrite=overwrite)


def _perception_identity(model: ComponentVAE) -> str:
    """A perception module's key in a latent cache: the hash of its weights and config, the same
    for a run's perception.pt and the shipped copy of it (xvoe.fingerprints.arrays_hash)."""
    arrays = {name: tensor.detach().cpu().numpy() for name, tensor in model.state_dict().items()}
    return arrays_hash(arrays, to_dict(model.config))


def encoder_key(model: ComponentVAE, device: torch.device | None = None) -> str:
    """What a latent cache's values hang on: the module (`_perception_identity`) and, where it is
    not float32, the precision it encodes in on `device` (its own by default): bfloat16 on CUDA
    moves latents far beyond float rounding, so a GPU's cache is not the CPU's."""
    dtype = autocast_dtype(device or device_of(model))
    return _perception_identity(model) + ("" if dtype == torch.float32 else f"-{str(dtype).removeprefix('torch.')}")


def split_cache(data: str | os.PathLike, perception: str) -> Path:
    """Where a test split's latent cache lies: beside the split, one per perception module and
    precision, DATA.latents-PERCEPTION.h5 (PERCEPTION: its `encoder_key`)."""
    data = Path(data)
    return data.with_name(f"{data.stem}.latents-{perception}.h5")


def check_cache(cache: str | os.PathLike, data: str | os.PathLike, perception: str | None = None,
                identity: dict | None = None) -> None:
    """An error unless the latent cache was encoded from this very split and, given
    `perception` (a `_perception_identity`), by that perception module. The split is known by
    the identity the cache records (`split_identity`: seed, config, videos, contents; `identity`,
    the split's, where the caller has it already: it hashes frames); a cache that records none,
    by the same path, generation config and video count (a file regenerated under the old name
    is another split)."""
    with open_latents(cache) as file:
        source, recorded = file.attrs.get("source", ""), file.attrs.get("split_identity")
        data_config = json.loads(file.attrs.get("config", "{}")).get("data")
        videos, encoder = file["mean"].shape[0], file.attrs.get("perception_identity")
    if recorded is not None and identity is not None:
        same = json.loads(recorded) == identity
    else:
        with store.open_dataset(data) as split:
            if recorded is not None:
                same = json.loads(recorded) == split_identity(split)
            else:
                same = (source == str(Path(data).resolve()) and data_config == store.config_of(split)
                        and videos == split["rgbd"].shape[0])
    if not same:
        found = f" ({describe_split(json.loads(recorded))})" if recorded is not None else ""
        raise XvoeError(f"{cache} was encoded from {source or 'an unknown split'}{found}, not from {data} as it is "
                        "now; remove it or encode again with xvoe encode --overwrite")
    if perception is not None and encoder != perception:
        raise XvoeError(f"{cache} was encoded by another perception module ({encoder or 'unrecorded'}) than the "
                        f"model's ({perception}); remove it or encode again with xvoe encode --overwrite")
