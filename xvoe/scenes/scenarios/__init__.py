"""Scenario templates and the registries that name them.

Each test scenario module samples every parameter from one seeded generator with
`sample(rng)` and offers `test_pair(rng, setting, frames)` (its settings in `SETTINGS`) and
`training(rng, with_wall, frames)`; the training-only groups offer `training` alone.
"""
from __future__ import annotations

from ..physics import Take
from . import blocking, collision, continuity, control, pass_behind, permanence

SCENARIOS = {
    "collision": collision,
    "blocking": blocking,
    "permanence": permanence,
    "continuity": continuity,
}

# The 11 test settings, in storage order.
TEST_SETTINGS: tuple[tuple[str, str], ...] = tuple(
    (name, setting) for name, module in SCENARIOS.items() for setting in module.SETTINGS)

TRAINING_GROUPS = {
    "control": control.training,
    "collision": collision.training,
    "blocking": blocking.training,
    "pass_behind": pass_behind.training,
    "permanence": permanence.training,
    "continuity": continuity.training,
}

__all__ = ["SCENARIOS", "TEST_SETTINGS", "TRAINING_GROUPS", "Take"]
