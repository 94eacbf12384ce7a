"""Explanations by identity: a seen object that goes out of sight and is seen again may be one
object, or two identical ones.

Under the second explanation the object seen before the gap (A) stops where it went out of
sight and stays there, and an identical object (B), there from the start, waits where the seen
one came back into sight and is the one seen after the gap. Where they wait is what Transformer
1 filled in for the object's first and last unseen frames: just past the edges of what hid it.
Both are drawn in every frame, behind the walls like every unseen object, so a wall lifted
before the gap shows B and one lifted after it shows A: the explanation then loses by the pixels
themselves. B's first sighting is scored as any object's is, under the latent prior
(`XPLScene.seen_motion`): its wait says nothing of how it came into sight. The two objects take
the seen object's slot and a free one; the scene of each explanation is the same `XPLScene`,
built from latents edited here.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from xvoe.models.reasoning import never_seen

__all__ = ["Identity", "identity_gap", "two_objects"]


class Identity(NamedTuple):
    """Which seen object may be two, and where its gap is."""

    slot: int           # the seen object's slot: B, the one seen after the gap, keeps it
    second: int         # the free slot A takes, the one seen before the gap
    last_seen: int      # A's last seen frame
    seen_again: int     # B's first seen frame


def identity_gap(visible: Tensor, occluder: Tensor, hidden: int) -> Identity | None:
    """The longest gap between two frames in which a moving object was seen (the earliest
    such object on a tie), and a free slot for the second object: a never-seen one other than
    `hidden` (the hidden object's). None where no object goes out of sight and comes back, or no
    slot is free. visible (T, K) and occluder (K,) bool."""
    free = [slot for slot in torch.where(never_seen(visible[None])[0])[0].tolist() if slot != hidden]
    best = None
    for slot in torch.where(visible.any(0) & ~occluder)[0].tolist():
        seen = torch.where(visible[:, slot])[0].tolist()
        for before, after in zip(seen, seen[1:]):
            if after - before > 1 and (best is None or after - before > best.seen_again - best.last_seen):
                best = Identity(slot, -1, before, after)
    if best is None or not free:
        return None
    return best._replace(second=free[0])


def two_objects(refined: Tensor, visible: Tensor, identity: Identity) -> tuple[Tensor, Tensor]:
    """The latents (T, K, D) and visibility (T, K) of the two-object explanation: A in the free
    slot, seen up to its last seen frame and then still at its first unseen frame's latent; B in
    the seen object's slot, still at its last unseen frame's latent until it is seen again."""
    slot, second, last_seen, seen_again = identity
    latents, seen = refined.clone(), visible.clone()
    latents[:, second], seen[:, second] = refined[:, slot], visible[:, slot]
    latents[last_seen + 1:, second] = refined[last_seen + 1, slot]
    seen[last_seen + 1:, second] = False
    latents[:seen_again, slot] = refined[seen_again - 1, slot]
    seen[:seen_again, slot] = False
    return latents, seen
