"""Reading TensorFlow's TFRecord files without TensorFlow: the record framing, `tf.train.Example`
and the `TensorProto` that `tf.io.serialize_tensor` writes, each parsed from its wire format.

A TFRecord file (optionally gzip-compressed) is a run of records, each: the data's length
(uint64, little-endian), the masked CRC-32C of those 8 bytes (uint32), the data, the masked
CRC-32C of the data (uint32). Every checksum is checked, so a damaged or foreign file gives a
one-line error (`TFRecordError`) instead of wrong arrays.
"""
from __future__ import annotations

import gzip
import math
import os
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import crc32c
import numpy as np

from ..errors import XvoeError
from ..resources import memory_problem

__all__ = ["TFRecordError", "records", "parse_example", "parse_tensor"]

_GZIP_MAGIC = b"\x1f\x8b"
_MASK_DELTA = 0xA282EAD8
# TensorFlow's DataType enum (tensorflow/core/framework/types.proto) for the types a video holds
_DTYPES = {1: np.float32, 2: np.float64, 3: np.int32, 4: np.uint8, 6: np.int8, 9: np.int64, 10: np.bool_}
# TensorProto's repeated value fields (packed), by field number, for tensors written without tensor_content
_VALUE_FIELDS = {5: "f4", 6: "f8", 7: "varint", 10: "varint", 11: "varint"}


class TFRecordError(XvoeError):
    """A file that is not a whole TFRecord file, or a record that is not what was expected."""


def _masked_crc(data: bytes | memoryview) -> int:
    """TFRecord's checksum: CRC-32C rotated right by 15 bits plus a constant, so that a CRC of
    data that holds CRCs is not itself weak."""
    crc = crc32c.crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


def _open(path: Path) -> BinaryIO:
    """The file's bytes, gunzipped if it starts with gzip's magic (X-VoE's files are gzip)."""
    with open(path, "rb") as probe:
        gzipped = probe.read(2) == _GZIP_MAGIC
    return gzip.open(path, "rb") if gzipped else open(path, "rb")  # noqa: SIM115 - closed by the caller


def _read_exactly(stream: BinaryIO, size: int, path: Path, what: str, offset: int) -> bytes:
    """`size` bytes, read a block at a time: a header claiming more than the file holds is
    found truncated, not met with a buffer of that size; one claiming more than this machine's
    memory is refused before the read."""
    if problem := memory_problem(size):
        raise TFRecordError(f"{path} claims {what} of {size:,} bytes at byte {offset}, which would {problem}")
    parts, left = [], size
    try:
        while left and (block := stream.read(min(left, _BLOCK))):
            parts.append(block)
            left -= len(block)
    except (EOFError, OSError, zlib.error) as error:    # a gzip stream cut short or corrupt
        raise TFRecordError(f"{path} is truncated or damaged: {what} at byte {offset}: {error}") from None
    if left:
        raise TFRecordError(f"{path} is truncated: {what} at byte {offset} has {size - left} of {size} bytes")
    return b"".join(parts)


_BLOCK = 1 << 26       # bytes read at a time (64 MiB)


def records(path: str | os.PathLike) -> Iterator[bytes]:
    """Every record of a TFRecord file (gzip or plain), its checksums checked."""
    path = Path(path)
    if not path.is_file():
        raise TFRecordError(f"{path}: no such file")
    with _open(path) as stream:
        offset = 0
        while True:
            try:
                header = stream.read(12)
            except (EOFError, OSError, zlib.error) as error:
                raise TFRecordError(f"{path} is truncated or not a TFRecord file at byte {offset}: {error}") from None
            if not header:
                return
            if len(header) < 12:
                raise TFRecordError(f"{path} is truncated: a record header at byte {offset} has {len(header)} "
                                    "of 12 bytes")
            length, length_crc = struct.unpack("<QI", header)
            if _masked_crc(header[:8]) != length_crc:
                raise TFRecordError(f"{path} is not a TFRecord file (bad length checksum at byte {offset})")
            data = _read_exactly(stream, length, path, "a record", offset + 12)
            checksum = _read_exactly(stream, 4, path, "a record's checksum", offset + 12 + length)
            (data_crc,) = struct.unpack("<I", checksum)
            if _masked_crc(data) != data_crc:
                raise TFRecordError(f"{path} is damaged: bad data checksum in the record at byte {offset}")
            offset += 16 + length
            yield data


def _count_records(path: str | os.PathLike) -> int:
    """How many whole records the file holds; a damaged file raises, as `records` does."""
    return sum(1 for _ in records(path))


# --- the protobuf wire format: just what Example and TensorProto need --------------------------

def _varint(data: memoryview, at: int) -> tuple[int, int]:
    value, shift = 0, 0
    while True:
        if at >= len(data) or shift > 63:
            raise ValueError("a varint runs past its message")
        byte = data[at]
        value |= (byte & 0x7F) << shift
        at += 1
        if byte < 0x80:
            return value, at
        shift += 7


def _fields(message: bytes | memoryview) -> Iterator[tuple[int, int, int | memoryview]]:
    """(field number, wire type, value) of each field: an int for varints, bytes otherwise."""
    data = memoryview(message)
    at = 0
    while at < len(data):
        key, at = _varint(data, at)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, at = _varint(data, at)
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            value, at = data[at:at + size], at + size
        elif wire == 2:
            size, at = _varint(data, at)
            value, at = data[at:at + size], at + size
        else:
            raise ValueError(f"wire type {wire} (groups) is not used by Example or TensorProto")
        if at > len(data) or number == 0:
            raise ValueError("a field runs past its message")
        yield number, wire, value


def _packed(wire: int, value, kind: str) -> list:
    """The values of a repeated scalar field, packed (wire type 2) or one per field."""
    if kind == "varint":
        if wire == 0:
            return [value]
        values, at, data = [], 0, memoryview(value)
        while at < len(data):
            item, at = _varint(data, at)
            values.append(item)
        return values
    return list(np.frombuffer(bytes(value), dtype="<" + kind))


def _feature(message: memoryview) -> list:
    """A tf.train.Feature's values: bytes_list (1), float_list (2) or int64_list (3)."""
    for number, _, inner in _fields(message):
        values: list = []
        for _, wire, value in _fields(inner):
            if number == 1:
                values.append(bytes(value))
            elif number == 2:
                values += _packed(wire, value, "f4")
            elif number == 3:
                values += _packed(wire, value, "varint")
        return values
    return []


def parse_example(record: bytes) -> dict[str, list]:
    """A tf.train.Example as {feature name: its values}: Example.features (1) is a Features,
    whose map field feature (1) holds entries of key (1) and Feature (2)."""
    parsed: dict[str, list] = {}
    try:
        for number, wire, features in _fields(record):
            if number != 1 or wire != 2:
                continue
            for entry_number, _, entry in _fields(features):
                if entry_number != 1:
                    continue
                name, value = "", memoryview(b"")
                for key, _, part in _fields(entry):
                    if key == 1:
                        name = bytes(part).decode("utf-8")
                    elif key == 2:
                        value = part
                parsed[name] = _feature(value)
    except (ValueError, UnicodeDecodeError) as error:
        raise TFRecordError(f"a record is not a tf.train.Example ({error})") from None
    return parsed


def parse_tensor(serialized: bytes) -> np.ndarray:
    """The array of a TensorProto as tf.io.serialize_tensor writes it: dtype (1), tensor_shape
    (2, its dims in field 2, each dim's size in field 1), and the values in tensor_content (4),
    or for a tensor written value by value, in its typed repeated field."""
    dtype, shape, content, values = None, [], None, []
    try:
        for number, wire, value in _fields(serialized):
            if number == 1:
                dtype = value
            elif number == 2:
                shape = [next((int(size) for n, _, size in _fields(dim) if n == 1), 0)
                         for n, _, dim in _fields(value) if n == 2]
            elif number == 4:
                content = bytes(value)
            elif number in _VALUE_FIELDS:
                values += _packed(wire, value, _VALUE_FIELDS[number])
    except ValueError as error:
        raise TFRecordError(f"a tensor is not a serialized TensorProto ({error})") from None
    if dtype not in _DTYPES:
        raise TFRecordError(f"a tensor has TensorFlow dtype {dtype}, which this reader does not know")
    count = math.prod(shape) if shape else 1       # Python's integers: a declared size never overflows
    if problem := memory_problem(count * np.dtype(_DTYPES[dtype]).itemsize):
        raise TFRecordError(f"a tensor declares shape {tuple(shape)}, which would {problem}")
    if content is not None:
        array = np.frombuffer(content, dtype=np.dtype(_DTYPES[dtype]).newbyteorder("<"))
    else:       # written value by value; a single value stands for all (TensorFlow's splat)
        array = np.asarray(values if len(values) != 1 else values * count, dtype=_DTYPES[dtype])
    if array.size != count:
        raise TFRecordError(f"a tensor of shape {tuple(shape)} holds {array.size} values, not {count}")
    return array.astype(_DTYPES[dtype], copy=False).reshape(shape)
