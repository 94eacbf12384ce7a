"""The test split's latent cache as a score reads it: the latents of every video, encoded once
per perception module and shared by every model and surprise definition that reads them.

The first score writes the cache beside the split (xvoe.training.latents, `split_cache`) and
the others read it; scores are the same with it or without.
"""
from __future__ import annotations

import os
from pathlib import Path

from ..errors import XvoeError
from ..outputs import claim_file, claim_scope
from ..training.latents import check_cache, encode_with, encoder_key, split_cache
from .scorer import Scorer

__all__ = ["latent_cache"]


@claim_scope()
def latent_cache(scorer: Scorer, data: str | os.PathLike, cache: str | os.PathLike | bool = True, *,
                 make: bool = True, progress: bool = False, identity: dict | None = None) -> Path | None:
    """The latent cache a scorer reads for the test split `data` (checked before): `cache`, or
    with True the split's own for the scorer's perception module (`split_cache`); None for a
    model without one, with `cache` False, or where it is missing and not to be made. One given
    is checked against the split and the perception (a one-line error for a stale or foreign
    one); the split's own, made from an earlier file of the split's name (a split generated again,
    a notebook's with other pairs), is derived data and made again. One to be made is claimed
    first (a folder that refuses it is named before the work; a run making it now is waited
    for, and its cache read), then written by the scorer's perception module. `identity`: the
    split's `split_identity`, where the caller has it."""
    if cache is False or scorer.vae is None:
        return None
    perception = encoder_key(scorer.vae)
    path = split_cache(data, perception) if cache is True else Path(cache)
    if _usable_cache(path, data, perception, identity, cache is True):
        return path
    if not make:
        return None
    # another run scoring this split with this perception makes the same cache: wait for it, then read it
    claim_file(path, overwrite=True, what="the latent cache", wait=True)
    if _usable_cache(path, data, perception, identity, cache is True):
        return path
    return encode_with(scorer.vae, data, path, overwrite=True, progress=progress, identity=identity)


def _usable_cache(path: Path, data: str | os.PathLike, perception: str, identity: dict | None, own: bool) -> bool:
    """Whether the cache at `path` is there and of this split and perception; one given (not
    the split's `own`) that is not is refused in one line."""
    if not path.exists():
        return False
    try:
        check_cache(path, data, perception, identity)
    except XvoeError:
        if not own:
            raise
        return False
    return True
