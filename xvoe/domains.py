"""Domains of numeric settings: the values each may take, declared beside its field.

The lowest layer, so that every config, of the benchmark as of the networks, can declare them
and a value is refused, naming its field, before any work.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any

from .errors import XvoeError

__all__ = ["Domain", "POSITIVE", "NON_NEGATIVE", "COUNT", "SHARE", "SEED", "PICTURE_SIZE", "DISPLAY_SIZE",
           "DEVICES", "TIME_LIMIT", "within", "check_config", "check_number"]


@dataclass(frozen=True)
class Domain:
    """The values a numeric setting may take: finite, from `low` to `high` (an end left out
    where open). Declared beside each field (`within`), so that a value is refused before work."""

    low: float = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def holds(self, value: float) -> bool:
        # an int of any size is finite; math.isfinite would overflow on one beyond a float
        if not isinstance(value, int) and not math.isfinite(value):
            return False
        above = value > self.low if self.open_low else value >= self.low
        below = value < self.high if self.open_high else value <= self.high
        return above and below

    def __str__(self) -> str:
        ends = [f"{'>' if self.open_low else '>='} {self.low}" if self.low > -math.inf else "",
                f"{'<' if self.open_high else '<='} {self.high}" if self.high < math.inf else ""]
        return "a finite number " + " and ".join(filter(None, ends))


POSITIVE = Domain(0, open_low=True)
NON_NEGATIVE = Domain(0)
COUNT = Domain(1)
SHARE = Domain(0, 1)
SEED = Domain(0, 2**63 - 1)     # what numpy's and torch's generators take, with room for seed + 1
PICTURE_SIZE = Domain(16, 512)  # pixels a side of a rendered or displayed frame
DISPLAY_SIZE = 128               # pixels a side of the scene drawn for people (xvoe/scenes/display.py)
DEVICES = "cpu, cuda, cuda:N or mps"     # the devices a user may name (xvoe/models/devices.py)
# seconds a model of your own may take for one batch (xvoe score --time-limit): generous, so
# that only a hang ends a run; here, below torch, for the command line's default
TIME_LIMIT = 600.0


def within(default: Any, domain: Domain) -> Any:
    """A dataclass field with its default and the Domain its values (or each item) must lie in."""
    return field(default=default, metadata={"domain": domain})


def check_config(config: Any, prefix: str = "") -> Any:
    """`config` if every field (of nested configs too) lies in its domain; else an error naming it."""
    for item in fields(config):
        value = getattr(config, item.name)
        if is_dataclass(value):
            check_config(value, f"{prefix}{item.name}.")
        else:
            check_number(item.metadata.get("domain"), prefix + item.name, value)
    return config


def check_number(domain: Domain | None, name: str, value: Any) -> Any:
    """`value` (each item of a tuple) if it lies in `domain`; else an error that names the setting."""
    for item in value if isinstance(value, tuple) else (value,):
        numeric = isinstance(item, (int, float)) and not isinstance(item, bool)
        if domain is not None and numeric and not domain.holds(item):
            raise XvoeError(f"{name} must be {domain}, not {item!r}")
    return value
