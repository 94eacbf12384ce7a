"""`xvoe import`: small TFRecords written here in the release's format (gzip, the features
raw_image, mask and slot, uint8 tensors as tf.io.serialize_tensor writes them) come back as
the same arrays, with the test labels where the reference's metrics put them; a truncated or
foreign file is refused in one line with nothing written."""
from __future__ import annotations

import gzip
import struct
from pathlib import Path

import numpy as np
import pytest

from xvoe.cli import main
from xvoe.scenes import store
from xvoe.scenes.released import _BLOCKS, _TEST_FILES, _downsample, _ids_of
from xvoe.scenes.tfrecord import _masked_crc, parse_example, parse_tensor, records

FRAMES, SIZE, SLOTS, PAIRS = 3, 8, 8, 2


# --- a minimal writer of the release's format (the protobuf wire format by hand) ---------------

def varint(value: int) -> bytes:
    out = bytearray()
    while True:
        out.append((value & 0x7F) | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            return bytes(out)


def field(number: int, payload: bytes | int) -> bytes:
    """A varint field (int) or a length-delimited one (bytes)."""
    if isinstance(payload, int):
        return varint(number << 3) + varint(payload)
    return varint(number << 3 | 2) + varint(len(payload)) + payload


def serialize_tensor(array: np.ndarray) -> bytes:
    """TensorProto: dtype DT_UINT8 (4), tensor_shape's dims, tensor_content."""
    shape = b"".join(field(2, field(1, int(size))) for size in array.shape)
    return field(1, 4) + field(2, shape) + field(4, np.ascontiguousarray(array).tobytes())


def example(features: dict[str, bytes | list[float]]) -> bytes:
    """tf.train.Example with a bytes_list (one value) or a packed float_list per feature."""
    entries = b""
    for name, value in features.items():
        inner = field(1, field(1, value)) if isinstance(value, bytes) else \
            field(2, field(1, np.asarray(value, "<f4").tobytes()))
        entries += field(1, field(1, name.encode()) + field(2, inner))
    return field(1, entries)


def framed(record: bytes) -> bytes:
    length = struct.pack("<Q", len(record))
    return length + struct.pack("<I", _masked_crc(length)) + record + struct.pack("<I", _masked_crc(record))


def write_tfrecord(path: Path, records_: list[bytes]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wb") as out:
        for record in records_:
            out.write(framed(record))


def make_video(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image (T, H, W, 4), masks (T, K, H, W, 1) of what each slot shows, their ids)."""
    image = rng.integers(0, 256, (FRAMES, SIZE, SIZE, 4), dtype=np.uint8)
    ids = rng.integers(0, SLOTS + 1, (FRAMES, SIZE, SIZE)).astype(np.uint8)
    masks = (ids[:, None] == np.arange(1, SLOTS + 1)[None, :, None, None]).astype(np.uint8)[..., None]
    return image, masks, ids


def video_record(image: np.ndarray, masks: np.ndarray, rng: np.random.Generator) -> bytes:
    slot = list(rng.normal(size=FRAMES * SLOTS * 4))
    return example({"raw_image": serialize_tensor(image), "mask": serialize_tensor(masks), "slot": slot})


def write_release(root: Path, seed: int = 0) -> dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]:
    """test/SCENARIO/eval-part-NNN.tfrecord, one block of PAIRS videos per file, and the videos
    by (scenario, record index)."""
    rng, videos = np.random.default_rng(seed), {}
    for scenario, files in _TEST_FILES.items():
        for part in range(files):
            found = []
            for pair in range(PAIRS):
                image, masks, ids = make_video(rng)
                videos[scenario, part * PAIRS + pair] = image, ids
                found.append(video_record(image, masks, rng))
            write_tfrecord(root / "test" / scenario / f"eval-part-{part:03d}.tfrecord", found)
    return videos


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("X-VoE")
    return root, write_release(root)


# --- the reader ------------------------------------------------------------------------------

def test_a_tensor_as_tensorflow_serializes_it_is_read():
    # tf.io.serialize_tensor(tf.constant([[1, 2], [3, 4]], tf.uint8)), byte for byte
    serialized = b'\x08\x04\x12\x08\x12\x02\x08\x02\x12\x02\x08\x02"\x04\x01\x02\x03\x04'
    np.testing.assert_array_equal(parse_tensor(serialized), np.array([[1, 2], [3, 4]], np.uint8))


def test_records_and_features_come_back(tmp_path):
    rng = np.random.default_rng(1)
    image, masks, _ = make_video(rng)
    path = tmp_path / "one.tfrecord"
    write_tfrecord(path, [video_record(image, masks, rng), b"", b"x" * 300])
    got = list(records(path))
    assert got[1:] == [b"", b"x" * 300]
    parsed = parse_example(got[0])
    assert sorted(parsed) == ["mask", "raw_image", "slot"] and len(parsed["slot"]) == FRAMES * SLOTS * 4
    np.testing.assert_array_equal(parse_tensor(parsed["raw_image"][0]), image)
    np.testing.assert_array_equal(parse_tensor(parsed["mask"][0]), masks)


def test_overlapping_masks_go_to_the_nearest_slot():
    masks = np.zeros((1, 3, 1, 4), np.uint8)
    masks[0, 2, 0, :] = 255       # slot 2 (a wall, near) everywhere; slot 1 over the last three pixels (amodal)
    masks[0, 1, 0, 1:] = 1
    masks[0, 0, 0, 3] = 1         # slot 0 claims no pixel alone: behind the others wherever it is
    depth = np.array([[[20, 80, 80, 80]]], np.uint8)
    depth[0, 0, 0] = 20
    ids, shared = _ids_of(masks, depth)
    np.testing.assert_array_equal(ids, [[[3, 3, 3, 3]]])
    assert shared == 3
    masks[0, 2, 0, 0], masks[0, 1, 0, 0] = 0, 1     # now slot 1 alone at pixel 0, the wall alone nowhere
    depth[0, 0, 0] = 10
    ids, shared = _ids_of(masks, depth)
    np.testing.assert_array_equal(ids, [[[2, 2, 2, 2]]])
    assert shared == 3


def test_downsampling_keeps_a_small_object_and_averages_colour():
    image = np.zeros((1, 8, 8, 4), np.uint8)
    image[..., :3] = 100
    image[..., 3] = 200                 # background far
    ids = np.zeros((1, 8, 8), np.uint8)
    ids[0, :, 4:] = 8                   # the wall, the right half, near
    image[0, :, 4:, 3] = 20
    image[0, :, 4:, :3] = 60
    ids[0, 1, 1] = 1                    # a one-pixel object in the top-left block: a quarter of it
    image[0, 1, 1] = (200, 0, 0, 40)
    ids[0, 4, 3:5] = 2                  # an object straddling the wall's edge: one pixel in each of two blocks
    image[0, 4, 3:5, 3] = 10
    rgbd, small = _downsample(image, ids, 4)
    assert small.shape == (1, 4, 4) and rgbd.shape == (1, 4, 4, 4)
    assert small[0, 0, 0] == 1 and rgbd[0, 0, 0, 3] == 40       # kept, at its own depth, not the background's
    np.testing.assert_array_equal(rgbd[0, 0, 0, :3], np.rint([(3 * 100 + 200) / 4, 75, 75]))   # area average
    assert small[0, 2, 1] == 2 and rgbd[0, 2, 1, 3] == 10       # in the first block it covers most
    assert (small[0, :, 2:] == 8).all() and (rgbd[0, :, 2:, 3] == 20).all()
    assert (small[0, :, :2] == 0).sum() == 6 and (rgbd[0, :, :2, 3][small[0, :, :2] == 0] == 200).all()


# --- the import --------------------------------------------------------------------------------

def test_the_test_split_round_trips_with_the_references_labels(release, tmp_path, capsys):
    root, videos = release
    out = tmp_path / "released.h5"
    assert main(["import", str(root), "--split", "test", "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    with store.open_dataset(out, "test") as file:
        labels = store.labels(file, store.TEST_LABELS)
        assert len(labels["pair"]) == len(videos)
        for (scenario, index), (image, ids) in videos.items():
            block, pair = divmod(index, PAIRS)
            setting, member, possible = _BLOCKS[block]
            row = np.flatnonzero((labels["scenario"] == scenario) & (labels["setting"] == setting)
                                 & (labels["pair"] == pair) & (labels["member"] == member))
            assert len(row) == 1
            assert labels["possible"][row[0]] == possible
            np.testing.assert_array_equal(file["rgbd"][row[0]], image)
            np.testing.assert_array_equal(file["ids"][row[0]], ids)
        # the schema's order: scenario by scenario, setting by setting, pair by pair, member 0 then 1
        assert list(dict.fromkeys(labels["scenario"])) == list(_TEST_FILES)
        assert list(labels["member"][:4]) == [0, 1, 0, 1] and list(labels["pair"][:4]) == [0, 0, 1, 1]
        assert list(labels["setting"][:2 * PAIRS * 3:2 * PAIRS]) == ["S1", "S2", "S3"]
        assert (labels["event_frame"] == -1).all()
        names = list(file.attrs["kind_names"])
        assert names[file["kind"][0, 7]] == "wall" and "object" in names
        columns = list(file["states"].attrs["state_columns"])
        first = videos["collision", 0][1]
        visible = file["states"][0][..., columns.index("visible")]
        np.testing.assert_array_equal(visible, (first[:, None] == np.arange(1, 9)[None, :, None, None]).any((2, 3)))


def test_the_training_split_round_trips(tmp_path):
    rng = np.random.default_rng(2)
    made = [make_video(rng) for _ in range(3)]
    write_tfrecord(tmp_path / "X-VoE" / "train" / "train-part-000.tfrecord",
                   [video_record(image, masks, rng) for image, masks, _ in made[:2]])
    write_tfrecord(tmp_path / "X-VoE" / "train" / "train-part-001.tfrecord", [video_record(*made[2][:2], rng)])
    out = tmp_path / "train.h5"
    assert main(["import", str(tmp_path / "X-VoE"), "--split", "train", "--out", str(out), "--quiet"]) == 0
    with store.open_dataset(out, "train") as file:
        for row, (image, _, ids) in enumerate(made):
            np.testing.assert_array_equal(file["rgbd"][row], image)
            np.testing.assert_array_equal(file["ids"][row], ids)
        assert file["has_wall"][:].tolist() == [bool((ids == 8).any()) for _, _, ids in made]


def copy_release(source: Path, target: Path) -> Path:
    for path in source.rglob("*.tfrecord"):
        (target / path.relative_to(source)).parent.mkdir(parents=True, exist_ok=True)
        (target / path.relative_to(source)).write_bytes(path.read_bytes())
    return target


def spoil_truncated_gzip(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-200])


def spoil_truncated_plain(path: Path) -> None:
    data = gzip.decompress(path.read_bytes())
    path.write_bytes(data[:-10])


def spoil_foreign(path: Path) -> None:
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)


def spoil_foreign_gzip(path: Path) -> None:
    path.write_bytes(gzip.compress(b"name,score\n" * 100))


def spoil_foreign_records(path: Path) -> None:
    write_tfrecord(path, [example({"image/encoded": b"\xff\xd8", "label": [1.0]})] * PAIRS)


def spoil_rgb_only(path: Path) -> None:
    rng = np.random.default_rng(3)
    image, masks, _ = make_video(rng)
    write_tfrecord(path, [video_record(image[..., :3], masks, rng)] * PAIRS)


@pytest.mark.parametrize("spoil,needle", [
    (spoil_truncated_gzip, "truncated"),
    (spoil_truncated_plain, "truncated"),
    (spoil_foreign, "not a TFRecord file"),
    (spoil_foreign_gzip, "not a TFRecord file"),
    (spoil_foreign_records, "is not an X-VoE video: no raw_image or mask feature"),
    (spoil_rgb_only, "without depth"),
])
def test_a_bad_file_gives_one_line_and_writes_nothing(release, tmp_path, capsys, spoil, needle):
    root = copy_release(release[0], tmp_path / "X-VoE")
    bad = root / "test" / "permanence" / "eval-part-002.tfrecord"
    spoil(bad)
    out = tmp_path / "out" / "released.h5"
    assert main(["import", str(root), "--split", "test", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and str(bad) in err, err
    assert not out.exists() and not out.parent.exists()       # not even the folder it would have made


def test_a_missing_file_or_an_uneven_scenario_is_refused(release, tmp_path, capsys):
    root = copy_release(release[0], tmp_path / "X-VoE")
    (root / "test" / "blocking" / "eval-part-005.tfrecord").unlink()
    assert main(["import", str(root), "--split", "test", "--out", str(tmp_path / "a.h5")]) == 2
    assert "blocking is incomplete" in capsys.readouterr().err
    write_tfrecord(root / "test" / "blocking" / "eval-part-005.tfrecord", [])
    assert main(["import", str(root), "--split", "test", "--out", str(tmp_path / "a.h5")]) == 2
    assert "not 6 equal blocks" in capsys.readouterr().err
    assert not (tmp_path / "a.h5").exists()


def test_a_training_set_with_a_gap_imports_with_a_warning(tmp_path, capsys):
    rng = np.random.default_rng(4)
    for part in (0, 2):         # train-part-001 is missing
        image, masks, _ = make_video(rng)
        write_tfrecord(tmp_path / "X-VoE" / "train" / f"train-part-{part:03d}.tfrecord",
                       [video_record(image, masks, rng)])
    out = tmp_path / "train.h5"
    assert main(["import", str(tmp_path / "X-VoE"), "--split", "train", "--out", str(out), "--quiet"]) == 0
    warned = capsys.readouterr().err.strip().splitlines()
    assert len(warned) == 1 and "incomplete" in warned[0] and "without train-part-001" in warned[0], warned
    with store.open_dataset(out, "train") as file:
        assert file["rgbd"].shape[0] == 2


def test_a_size_that_does_not_divide_the_release_is_refused(release, tmp_path, capsys):
    out = tmp_path / "r.h5"
    assert main(["import", str(release[0]), "--split", "test", "--size", "3", "--out", str(out), "--quiet"]) == 2
    assert "--size 3 does not divide the release's 8x8 frames" in capsys.readouterr().err
    assert not out.exists()


def test_scoring_the_release_at_its_own_size_names_the_import_option(release, tmp_path, capsys):
    data = tmp_path / "released.h5"
    assert main(["import", str(release[0]), "--split", "test", "--out", str(data), "--quiet"]) == 0
    assert main(["score", "--model", "xpl", "--data", str(data), "--out", str(tmp_path / "s.csv"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "holds 8x8 frames" in err and err.endswith("import the release again with xvoe import --size 32"), err
