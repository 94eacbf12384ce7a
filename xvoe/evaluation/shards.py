"""A split scored in parts: the rows of part I of N (`shard_rows`, whole batches), and the
parts joined into the files one run would have written, byte for byte (`merge_scores`).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import XvoeError
from ..outputs import claim_file, claim_scope
from .score_headers import check_curves_of, curves_arrays, header_of
from .score_writer import write_score_files

__all__ = ["batch_count", "merge_scores", "shard_rows"]


def batch_count(count: int, videos_per_batch: int) -> int:
    """The batches of `count` videos: the most parts a split can be cut into."""
    return -(-count // videos_per_batch)


def shard_rows(count: int, videos_per_batch: int, shard: tuple[int, int]) -> tuple[int, int]:
    """Rows [first, last) of part I of N: whole batches, so each video is scored in the batch a
    single run would score it in."""
    index, parts = shard
    if not 0 <= index < parts:
        raise XvoeError(f"--shard must be I/N with 0 <= I < N, not {index}/{parts}")
    batches = batch_count(count, videos_per_batch)
    if parts > batches:
        raise XvoeError(f"cannot cut {batches} batches of {videos_per_batch} videos into {parts} shards")
    first, last = index * batches // parts, (index + 1) * batches // parts
    return first * videos_per_batch, min(count, last * videos_per_batch)


@claim_scope()
def merge_scores(parts: list[str | Path], out: str | Path, overwrite: bool = False) -> Path:
    """Join the score files of `xvoe score --shard` (and their curves) into the files one run
    would have written, byte for byte; an error unless they are the parts of one split."""
    if not parts:
        raise XvoeError("--merge needs at least one part")
    out = claim_file(out, overwrite)
    curves_path = claim_file(out.with_suffix(".curves.npz"), overwrite, what="the curves beside --out")
    found = []
    for part in map(Path, parts):
        if not part.is_file() or not part.with_suffix(".curves.npz").is_file():
            raise XvoeError(f"{part} is not a scores file with its curves beside it")
        with open(part, newline="") as handle:      # the CSV's own line ends, kept
            lines = handle.read().splitlines(keepends=True)
        if len(lines) < 2:
            raise XvoeError(f"{part} holds no scores")
        found.append((int(lines[1].split(",", 1)[0]), part, lines))
    found.sort(key=lambda item: item[0])
    columns, expected, rows, arrays = found[0][2][0], 0, [], {}
    for first, part, lines in found:
        if lines[0] != columns:
            raise XvoeError(f"{part} has other columns than {found[0][1]}: the parts of one run have the same")
        if first != expected:
            raise XvoeError(f"the parts do not follow each other: {part} starts at video {first}, not {expected}")
        expected += len(lines) - 1
        rows += lines[1:]
        curves = part.with_suffix(".curves.npz")
        saved = curves_arrays(curves)
        check_curves_of(part, curves, header_of(curves, saved))
        for name, values in saved.items():
            arrays.setdefault(name, []).append(_without_digest(values) if name == "header" else values)
        if len(set(arrays.get("header", []))) > 1:
            raise XvoeError(f"{part} was scored with other settings than {found[0][1]} (their headers differ)")
    headers = arrays.pop("header", ["{}"])      # the parts' own, less their digests: the whole file's is written
    write_score_files(out, curves_path, "".join([columns, *rows]), json.loads(headers[0]),
                      {name: np.concatenate(values) for name, values in arrays.items()})
    return out


def _without_digest(header: np.ndarray) -> str:
    """A part's header without its own scores' digest: what the parts of one run share."""
    found = json.loads(str(header))
    found.pop("scores_digest", None)
    return json.dumps(found, sort_keys=True)
