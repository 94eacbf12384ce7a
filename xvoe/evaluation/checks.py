"""The harness a model answering `surprise(videos)` passes before its scores are written.

A broken model otherwise looks like a weak one: scores that depend on the batch or on the
order of the videos, that change on a repeat, that are NaN for some videos or the same for
all, still give an accuracy. Each check names itself in a one-line error.

The batch checks score a small seeded sample of the videos again: `_SAMPLE` videos in four
passes (one batch, a repeat, another order, one at a time), 32 video scorings whatever the
split's size, in which every sampled video is seen at another place in its batch and in a
batch of another size. The finite and spread checks read the scores of every video, which
the scoring computes anyway; the finite check is never skipped, as no metric can be taken
of a score that is not a number.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..errors import XvoeError

__all__ = ["ScoreBatch", "sample_rows", "check_batches", "check_finite", "check_spread"]

_SAMPLE = 8          # videos scored again in other batches: enough to move each one, cheap on any split
_SEED = 0            # the sample is drawn from this seed
_RELATIVE = 1e-4     # float tolerance: a batched matrix product may round differently from a single one
_ABSOLUTE = 1e-6     # ... and relative to the largest surprise, for frames near zero

# per-frame surprise (B, T) of the sample's videos at these positions, in this order, as one batch
ScoreBatch = Callable[[np.ndarray], np.ndarray]


def sample_rows(first: int, last: int, count: int = _SAMPLE) -> np.ndarray:
    """The rows in [first, last) the batch checks score again: `count` of them, sorted, drawn from `_SEED`."""
    rows = np.arange(first, last)
    if len(rows) <= count:
        return rows
    return np.sort(np.random.default_rng(_SEED).choice(rows, count, replace=False))


def check_batches(score_batch: ScoreBatch, rows: np.ndarray, model: str) -> None:
    """The sample scored as one batch, again, in another order and one video at a time gives
    the same per-frame surprise; a one-line `XvoeError` naming the first check that fails."""
    positions = np.arange(len(rows))
    reference = score_batch(positions)
    check_finite(reference, rows, model)
    _compare(reference, score_batch(positions), rows, model, "repeat", "scored twice in the same batch")
    order = np.roll(positions, 1)       # every video one place on
    shuffled = np.empty_like(reference)
    shuffled[order] = score_batch(order)
    _compare(reference, shuffled, rows, model, "order", "scored in another order")
    singles = np.concatenate([score_batch(positions[i:i + 1]) for i in positions])
    _compare(reference, singles, rows, model, "batch size",
             f"scored one at a time and in one batch of {len(rows)}")


def check_finite(values: np.ndarray, rows: np.ndarray, model: str) -> None:
    """Every video's per-frame surprise (B, T) is a finite number."""
    bad = rows[~np.isfinite(values).all(axis=1)]
    if len(bad):
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise _failed(model, "finite", f"its surprise is NaN or infinite for video {bad[0]}{more}", skippable=False)


def check_spread(scores: np.ndarray, model: str) -> None:
    """The videos' scores are not all equal: equal scores rank nothing, and every pair would be a tie."""
    if len(scores) > 1 and np.all(scores == scores[0]):
        raise _failed(model, "spread", f"all {len(scores)} videos score {scores[0]:.6g}, which tells none from another")


def _compare(reference: np.ndarray, other: np.ndarray, rows: np.ndarray, model: str, check: str, how: str) -> None:
    scale = float(np.abs(reference).max(initial=0.0))
    close = np.isclose(other, reference, rtol=_RELATIVE, atol=_ABSOLUTE * scale)
    if close.all():
        return
    worst = np.unravel_index(np.argmax(np.abs(other - reference)), reference.shape)
    raise _failed(model, check, f"video {rows[worst[0]]} {how} gives {other[worst]:.6g} at frame {worst[1]}, "
                                f"not {reference[worst]:.6g}")


def _failed(model: str, check: str, what: str, skippable: bool = True) -> XvoeError:
    """The one line of a failed check: which, what was seen, and how to score the model anyway."""
    anyway = "; --no-checks scores it as it is" if skippable else ""
    return XvoeError(f"the model {model} failed the check {check!r}: {what}{anyway}")
