"""The HDF5 schema, atomic writes, determinism across workers, shards and merging."""
import hashlib
import json

import h5py
import numpy as np
import pytest

from xvoe.errors import XvoeError
from xvoe.scenes import store
from xvoe.scenes.generate import GenerateConfig, generate, merge
from xvoe.scenes.render import STATE_COLUMNS
from xvoe.scenes.scenarios import TEST_SETTINGS


def sha256(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_test_schema(test_file):
    with store.open_dataset(test_file) as f:
        n = 8 * len(TEST_SETTINGS) * 2
        assert f["rgbd"].shape == (n, 15, 64, 64, 4) and f["rgbd"].dtype == np.uint8
        assert f["rgbd"].chunks == (1, 15, 64, 64, 4) and f["rgbd"].compression == "gzip"
        assert f["ids"].shape == (n, 15, 64, 64) and f["ids"].dtype == np.uint8
        assert f["states"].shape == (n, 15, 8, len(STATE_COLUMNS)) and f["states"].dtype == np.float32
        columns = list(f["states"].attrs["state_columns"])
        assert {"x", "y", "size", "lane", "present", "visible"} <= set(columns)
        assert f["kind"].shape == (n, 8) and f["kind"].dtype == np.int8
        assert list(f.attrs["kind_names"])[:5] == ["none", "ball", "cube", "wall", "window_wall"]
        assert f["color"].shape == (n, 8, 3) and f["color"].dtype == np.uint8
        assert f["possible"].dtype == np.bool_ and f["pair"].shape == (n,)
        assert set(store.strings(f, "scenario")) == {"collision", "blocking", "permanence", "continuity"}
        assert set(store.strings(f, "setting")) == {"S1", "S2", "S3"}
        assert list(f["member"][:4]) == [0, 1, 0, 1]
        config = json.loads(f.attrs["config"])
        assert config["pairs"] == 8 and config["size"] == 64 and f.attrs["seed"] == 3
        assert f.attrs["generator_version"] and f.attrs["xvoe_schema"] == store.SCHEMA_VERSION


def test_every_setting_has_its_pairs_and_labels(test_data):
    for scenario, setting in TEST_SETTINGS:
        mask = (test_data["scenario"] == scenario) & (test_data["setting"] == setting)
        assert mask.sum() == 16
        assert sorted(test_data["pair"][mask][::2]) == list(range(8))
        member0 = mask & (test_data["member"] == 0)
        member1 = mask & (test_data["member"] == 1)
        assert test_data["possible"][member0].all()
        assert test_data["possible"][member1].all() == (setting == "S2")


def test_ids_and_visibility_agree(test_data):
    """The visible column is the share of an object's silhouette that its id pixels cover."""
    ids = test_data["ids"]
    visible = test_data["states"][..., list(test_data["columns"]).index("visible")]
    for slot in range(8):
        seen = (ids == slot + 1).any(axis=(2, 3))
        assert np.array_equal(seen, visible[..., slot] > 0)


def test_depth_orders_the_lanes(test_data):
    """Walls are nearer than objects, objects nearer than the far background."""
    depth = test_data["rgbd"][..., 3]
    names = test_data["kind_names"]
    kind_of_pixel = np.take_along_axis(
        np.concatenate([np.zeros_like(test_data["kind"][:, :1]), test_data["kind"]], axis=1)[:, None, None, None, :],
        test_data["ids"][..., None].astype(np.int64), axis=-1)[..., 0]
    wall = np.isin(kind_of_pixel, [names.index("wall"), names.index("window_wall")])
    solid = np.isin(kind_of_pixel, [names.index("ball"), names.index("cube")])
    assert depth[wall].max() < depth[solid].min()
    assert depth[solid].max() < 255
    assert (depth[test_data["ids"] == 0] > depth[solid].min()).mean() > 0.9   # background and most floor behind


def test_train_schema(train_file):
    with store.open_dataset(train_file) as f:
        assert f["rgbd"].shape == (96, 15, 64, 64, 4)
        groups = set(store.strings(f, "group"))
        assert groups == {"control", "collision", "blocking", "pass_behind", "permanence", "continuity"}
        assert f["has_wall"].dtype == np.bool_ and 0 < f["has_wall"][:].mean() < 1
        assert "scenario" not in f


def test_same_seed_same_bytes_whatever_the_workers(tmp_path):
    config = GenerateConfig("test", pairs=2, seed=11)
    one = generate(config, tmp_path / "one.h5", workers=1, progress=False)
    two = generate(config, tmp_path / "two.h5", workers=2, progress=False)
    assert sha256(one) == sha256(two)
    other = generate(GenerateConfig("test", pairs=2, seed=12), tmp_path / "other.h5", progress=False)
    assert sha256(one) != sha256(other)


def test_size_and_frames_flags(tmp_path):
    """The size flag changes the picture, not the physics: states scale with the frame size."""
    small = generate(GenerateConfig("train", videos=6, size=32, frames=20), tmp_path / "s.h5", progress=False)
    large = generate(GenerateConfig("train", videos=6, size=64, frames=20), tmp_path / "l.h5", progress=False)
    with store.open_dataset(small) as s, store.open_dataset(large) as g:
        assert s["rgbd"].shape == (6, 20, 32, 32, 4) and s["ids"].shape == (6, 20, 32, 32)
        columns = list(s["states"].attrs["state_columns"])
        for name in ("x", "y", "size", "vx", "vy"):
            i = columns.index(name)
            np.testing.assert_allclose(s["states"][..., i], g["states"][..., i] / 2, rtol=1e-5, atol=1e-4)
        present = columns.index("present")
        np.testing.assert_array_equal(s["states"][..., present], g["states"][..., present])


def test_shards_merge_into_the_unsharded_file(tmp_path):
    config = GenerateConfig("test", pairs=3, seed=4)
    whole = generate(config, tmp_path / "whole.h5", progress=False)
    parts = [generate(config, tmp_path / f"part{i}.h5", shard=(i, 3), progress=False) for i in (2, 0, 1)]
    merged = merge(parts, tmp_path / "merged.h5", progress=False)
    with h5py.File(whole) as a, h5py.File(merged) as b:
        assert set(a) == set(b)
        for name in a:
            np.testing.assert_array_equal(a[name][:], b[name][:], err_msg=name)
        assert a.attrs.keys() == b.attrs.keys()
        assert all(np.array_equal(a.attrs[k], b.attrs[k]) for k in a.attrs)


def test_merge_refuses_incomplete_or_mixed_shards(tmp_path):
    config = GenerateConfig("train", videos=6, seed=1)
    parts = [generate(config, tmp_path / f"p{i}.h5", shard=(i, 3), progress=False) for i in range(3)]
    with pytest.raises(XvoeError, match="do not make up"):
        merge(parts[:2], tmp_path / "m.h5")
    with pytest.raises(XvoeError, match="do not make up"):
        merge(parts + parts[:1], tmp_path / "m.h5")
    stranger = generate(GenerateConfig("train", videos=6, seed=2), tmp_path / "s.h5", shard=(2, 3), progress=False)
    with pytest.raises(XvoeError, match="another run"):
        merge(parts[:2] + [stranger], tmp_path / "m.h5")
    whole = generate(config, tmp_path / "whole.h5", progress=False)
    with pytest.raises(XvoeError, match="not a shard"):
        merge([whole], tmp_path / "m.h5")
    assert not (tmp_path / "m.h5").exists()


def test_existing_output_is_refused_and_kept(tmp_path):
    out = tmp_path / "out.h5"
    out.write_bytes(b"precious")
    with pytest.raises(XvoeError, match="exists"):
        generate(GenerateConfig("train", videos=2), out, progress=False)
    assert out.read_bytes() == b"precious"
    generate(GenerateConfig("train", videos=2), out, overwrite=True, progress=False)
    with store.open_dataset(out) as f:
        assert f["rgbd"].shape[0] == 2


def test_a_crash_leaves_no_file(tmp_path, monkeypatch):
    import xvoe.scenes.generate as gen

    calls = {"n": 0}
    real = gen.make_unit

    def failing(config, unit):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("simulated crash")
        return real(config, unit)

    monkeypatch.setattr(gen, "make_unit", failing)
    with pytest.raises(RuntimeError):
        gen.generate(GenerateConfig("train", videos=5), tmp_path / "crash.h5", workers=1, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_open_dataset_rejects_foreign_files(tmp_path):
    with pytest.raises(XvoeError, match="no such file"):
        store.open_dataset(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("not hdf5")
    with pytest.raises(XvoeError, match="not an HDF5 file"):
        store.open_dataset(tmp_path / "text.h5")
    with h5py.File(tmp_path / "plain.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(XvoeError, match="not an xvoe dataset"):
        store.open_dataset(tmp_path / "plain.h5")
    with h5py.File(tmp_path / "future.h5", "w") as f:
        f.attrs["xvoe_schema"] = store.SCHEMA_VERSION + 1
    with pytest.raises(XvoeError, match="schema version"):
        store.open_dataset(tmp_path / "future.h5")


@pytest.mark.parametrize("kwargs,match", [
    ({"split": "val"}, "split"), ({"size": 8}, "size"), ({"frames": 5}, "frames"),
    ({"videos": 0}, "videos must be a finite number >= 1"), ({"seed": -1}, "seed")])
def test_bad_config_is_refused(kwargs, match):
    with pytest.raises(XvoeError, match=match):
        GenerateConfig(**kwargs)


def test_bad_shard_is_refused(tmp_path):
    for shard in ((3, 3), (-1, 2), (0, 0)):
        with pytest.raises(XvoeError, match="shard"):
            generate(GenerateConfig("train", videos=4), tmp_path / "x.h5", shard=shard, progress=False)
    assert not (tmp_path / "x.h5").exists()
