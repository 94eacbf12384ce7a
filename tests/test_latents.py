"""The latent cache: what `xvoe encode` writes and the later stages read."""
import json

import h5py
import numpy as np
import pytest
import torch

from xvoe.errors import XvoeError
from xvoe.models.perception import normalise
from xvoe.scenes.generate import GenerateConfig, generate
from xvoe.training.data import masked_inputs, visible_threshold
from xvoe.training.latents import _read_latents, _sha256_of, encode_split, open_latents
from xvoe.training.perception import load_perception, train_perception

TINY = dict(image_size=16, broadcast_size=4, latent_dim=4, cnn_channels=(8, 8), cnn_hidden=16, decoder_channels=8)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("cache")
    data = generate(GenerateConfig("train", videos=5, size=16, seed=12), root / "train16.h5", workers=1,
                    progress=False)
    train_perception(data, root / "run", steps=2, batch_size=4, model_overrides=TINY, progress=False, threads=1)
    return data, root / "run"


def test_cache_round_trip(trained, tmp_path):
    data, run_dir = trained
    path = encode_split(run_dir, data, tmp_path / "latents.h5", videos_per_batch=2, progress=False)
    cache = _read_latents(path)
    with h5py.File(data) as file:
        ids, states = file["ids"][:], file["states"][:]
        columns = list(file["states"].attrs["state_columns"])
        first_frames = file["rgbd"][0]
    n, t, k = states.shape[:3]
    assert cache.mean.shape == cache.std.shape == (n, t, k, 4) and cache.mean.dtype == np.float32
    assert cache.visible.shape == cache.present.shape == (n, t, k) and cache.visible.dtype == bool
    assert cache.background_mean.shape == (n, t, 4)
    assert np.isfinite(cache.mean).all() and (cache.std > 0).all()
    pixels = np.stack([(ids == s + 1).sum((2, 3)) for s in range(k)], axis=-1)
    assert np.array_equal(cache.pixels, pixels)
    assert np.array_equal(cache.visible, pixels > visible_threshold(16))
    assert np.array_equal(cache.present, states[..., columns.index("present")] > 0.5)
    # every empty slot holds the one posterior of the blank input
    empty = pixels == 0
    assert empty.any() and np.allclose(cache.mean[empty], cache.mean[empty][0])
    # the means are the model's posterior of each slot's masked frame
    model, _ = load_perception(run_dir)
    parts = masked_inputs(normalise(torch.as_tensor(first_frames)), torch.as_tensor(ids[0]), k)
    with torch.no_grad():
        mean, _ = model.posterior(parts["objects"])
    np.testing.assert_allclose(cache.mean[0][parts["object_frame"].numpy(), parts["object_slot"].numpy()],
                               mean.numpy(), rtol=1e-5, atol=1e-6)
    assert cache.attrs["xvoe_latents"] == 1
    assert cache.attrs["perception_sha256"] == _sha256_of(run_dir / "perception.pt")
    assert cache.attrs["perception_checkpoint"] == str((run_dir / "perception.pt").resolve())
    assert cache.attrs["source"] == str(data.resolve()) and cache.attrs["source_split"] == "train"
    assert json.loads(cache.attrs["config"])["perception"]["latent_dim"] == 4
    with pytest.raises(XvoeError, match="exists"):
        encode_split(run_dir, data, path, progress=False)


def test_cache_refuses_data_at_another_resolution(trained, tmp_path):
    _, run_dir = trained
    other = generate(GenerateConfig("train", videos=1, size=32, seed=1), tmp_path / "train32.h5", workers=1,
                     progress=False)
    with pytest.raises(XvoeError, match="32x32 frames but the checkpoint .* works at 16x16"):
        encode_split(run_dir, other, tmp_path / "latents.h5", progress=False)
    assert not (tmp_path / "latents.h5").exists()


def test_a_split_file_is_not_a_cache(trained):
    data, _ = trained
    with pytest.raises(XvoeError, match="not an xvoe latent cache"):
        open_latents(data)


