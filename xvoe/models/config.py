"""Config dataclasses as data: to and from a checkpoint's dicts, and changed field by field.

Every size a network uses is a field of a config dataclass, so a checkpoint that stores its
config can rebuild its model; these helpers serve every config, of any layer.
"""
from __future__ import annotations

import types
import typing
from dataclasses import asdict, fields, is_dataclass, replace
from typing import Any

from ..errors import XvoeError


def to_dict(config: Any) -> dict:
    """A dataclass config as plain JSON-able data (tuples become lists)."""
    return asdict(config)


def from_dict(cls: type, data: dict) -> Any:
    """Rebuild a (possibly nested) config dataclass from `to_dict` output; unknown keys are an error."""
    known = {f.name for f in fields(cls)}
    unknown = set(data) - known
    if unknown:
        raise XvoeError(f"{cls.__name__} has no field(s) {', '.join(sorted(unknown))}")
    hints = typing.get_type_hints(cls)
    values = {}
    for name, value in data.items():
        target = _nested_dataclass(hints[name])
        if target is not None and isinstance(value, dict):
            value = from_dict(target, value)
        elif isinstance(value, list):
            value = tuple(value)
        values[name] = value
    return cls(**values)


def _nested_dataclass(annotation: Any) -> type | None:
    """The config dataclass a field's type names, also inside `X | None`."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        found = [a for a in typing.get_args(annotation) if is_dataclass(a)]
        return found[0] if found else None
    return annotation if is_dataclass(annotation) else None


def override(config: Any, **changes: Any) -> Any:
    """A copy of `config` with the given fields changed; None values are ignored."""
    return replace(config, **{k: v for k, v in changes.items() if v is not None})


def override_resumed(config: Any, changes: dict | None, may_change: tuple[str, ...] = (), what: str = "run") -> Any:
    """`override` for the model config of a resumed run, which keeps its network: a change of any
    field outside `may_change` is an error rather than silently ignored (a value equal to the
    checkpoint's is not a change)."""
    changes = {k: v for k, v in (changes or {}).items() if v is not None}
    config = replace(config, **{k: v for k, v in changes.items() if k in may_change})
    shaping = sorted(k for k, v in changes.items() if k not in may_change and replace(config, **{k: v}) != config)
    if shaping:
        allowed = f"only {', '.join(may_change)} may change" if may_change else "none of it may change"
        raise XvoeError(f"a resumed {what} keeps its network: of its config {allowed}, not {', '.join(shaping)}")
    return config
