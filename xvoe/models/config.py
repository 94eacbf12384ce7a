"""Config dataclasses as data: to and from a checkpoint's dicts, and changed field by field.

Every size a network uses is a field of a config dataclass, so a checkpoint that stores its
config can rebuild its model; these helpers serve every config, of any layer.
"""
from __future__ import annotations

import types
import typing
from dataclasses import asdict, fields, is_dataclass, replace
from typing import Any

from ..domains import Domain, check_config, check_number
from ..errors import XvoeError

__all__ = ["parse_field", "to_dict", "from_dict", "override", "override_resumed", "field_type",
           "split_assignment", "parse_value"]


def _domain_of(cls: type, name: str) -> Domain | None:
    """The declared Domain of a config field (a dotted name reaching into nested configs)."""
    head, _, rest = name.partition(".")
    found = {f.name: f for f in fields(cls)}.get(head)
    if found is None:
        return None
    if rest:
        nested = _nested_dataclass(typing.get_type_hints(cls)[head])
        return _domain_of(nested, rest) if nested else None
    return found.metadata.get("domain")


def _check_value(cls: type, name: str, value: Any) -> Any:
    """`value` if it lies in the domain of `cls`'s field `name` (each item of a tuple); else an
    error that names the field."""
    return check_number(_domain_of(cls, name), name, value)


def parse_field(cls: type, name: str, text: str) -> Any:
    """A command line's value of `cls`'s field `name`: parsed as its type, checked against its domain."""
    kind = field_type(cls, name)
    try:
        value = parse_value(kind, text)
    except XvoeError as error:
        raise XvoeError(f"{name}: {error}") from None
    return _check_value(cls, name, value)


def to_dict(config: Any) -> dict:
    """A dataclass config as plain JSON-able data (tuples become lists)."""
    return asdict(config)


# Fields removed after the shipped checkpoints (xvoe/weights) stored them, each with the value every
# recipe held (their records: docs/log/decisions-2026-11.md). A stored config with that value loads
# without it; a field that no shipped checkpoint holds is no longer known at all.
_RETIRED: dict[str, dict[str, Any]] = {
    "PerceptionConfig": {"where_latents": False, "where_scale": 0.5, "amodal": False, "cut_share": 0.0},
    "XPLConfig": {"wall_refill": 0.0, "proposal_sees_seen": False, "latent_weights": (), "weigh_by_picture": False,
                  "fill_from_neighbours": False, "line_between_only": False},
    "PhyDNetConfig": {"lstm_chrono_frames": 0},
}


def from_dict(cls: type, data: dict, where: str = "") -> Any:
    """Rebuild a (possibly nested) config dataclass from `to_dict` output; unknown keys are an
    error, and so are a value not of its field's type and a retired field (`_RETIRED`) set to
    anything but the value it always held. `where`: the config's key in the errors (the class
    name by default)."""
    where = where or cls.__name__
    if not isinstance(data, dict):
        raise XvoeError(f"{where} is a {type(data).__name__}, not a dict of {cls.__name__} fields")
    data = _without_retired(cls, data)
    known = {f.name for f in fields(cls)}
    unknown = set(data) - known
    if unknown:
        raise XvoeError(f"{where} has no field(s) {', '.join(sorted(unknown))} ({cls.__name__} has not)")
    hints = typing.get_type_hints(cls)
    values = {}
    for name, value in data.items():
        target = _nested_dataclass(hints[name])
        if target is not None and isinstance(value, dict):
            value = from_dict(target, value, f"{where}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        if target is None and not _holds_type(hints[name], value):
            raise XvoeError(f"{where}.{name} is {value!r}, not {_type_name(hints[name])}")
        values[name] = value
    return check_config(cls(**values))


def _holds_type(kind: Any, value: Any) -> bool:
    """Whether `value` is of a config field's type `kind` (an int is a float too; a bool is
    neither; a tuple's items each of its item type): a stored config of the wrong types is
    refused by name instead of failing wherever the network first uses the value."""
    if isinstance(kind, types.UnionType) or typing.get_origin(kind) is typing.Union:
        return any(_holds_type(option, value) for option in typing.get_args(kind))
    if typing.get_origin(kind) is tuple:
        items = typing.get_args(kind)[:1] or (Any,)
        return isinstance(value, tuple) and all(_holds_type(items[0], item) for item in value)
    if kind is type(None):
        return value is None
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return kind is Any or not isinstance(kind, type) or isinstance(value, kind)


def _type_name(kind: Any) -> str:
    """A field's type in words, for an error."""
    if isinstance(kind, types.UnionType) or typing.get_origin(kind) is typing.Union:
        return " or ".join(_type_name(option) for option in typing.get_args(kind))
    if typing.get_origin(kind) is tuple:
        return f"a list of {_type_name(typing.get_args(kind)[0])}" if typing.get_args(kind) else "a list"
    if kind is type(None):
        return "none"
    return f"a {getattr(kind, '__name__', kind)}"


def _without_retired(cls: type, data: dict) -> dict:
    retired = _RETIRED.get(cls.__name__, {})
    for name, held in retired.items():
        value = data.get(name, held)
        if (tuple(value) if isinstance(value, list) else value) != held:
            raise XvoeError(f"this {cls.__name__} was made with {name}={value!r}, a setting xvoe no longer has")
    return {key: value for key, value in data.items() if key not in retired}


def _nested_dataclass(annotation: Any) -> type | None:
    """The config dataclass a field's type names, also inside `X | None`."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        found = [a for a in typing.get_args(annotation) if is_dataclass(a)]
        return found[0] if found else None
    return annotation if is_dataclass(annotation) else None


def override(config: Any, **changes: Any) -> Any:
    """A copy of `config` with the given fields changed; None values are ignored. A dotted
    name (`dynamics.hidden`) changes a field of a nested config."""
    flat = {k: v for k, v in changes.items() if v is not None and "." not in k}
    nested: dict[str, dict[str, Any]] = {}
    for key, value in changes.items():
        if value is not None and "." in key:
            head, _, rest = key.partition(".")
            nested.setdefault(head, {})[rest] = value
    for head, inner in nested.items():
        if head not in {f.name for f in fields(config)} or not is_dataclass(getattr(config, head)):
            raise XvoeError(f"{type(config).__name__} has no nested config {head!r}")
        flat[head] = override(getattr(config, head), **inner)
    return check_config(replace(config, **flat))


def override_resumed(config: Any, changes: dict | None, may_change: tuple[str, ...] = (), what: str = "run") -> Any:
    """`override` for the model config of a resumed run, which keeps its network: a change of any
    field outside `may_change` is an error rather than silently ignored (a value equal to the
    checkpoint's is not a change)."""
    changes = {k: v for k, v in (changes or {}).items() if v is not None}
    config = override(config, **{k: v for k, v in changes.items() if k in may_change})
    shaping = sorted(k for k, v in changes.items() if k not in may_change and override(config, **{k: v}) != config)
    if shaping:
        allowed = f"only {', '.join(may_change)} may change" if may_change else "none of it may change"
        raise XvoeError(f"a resumed {what} keeps its network: of its config {allowed}, not {', '.join(shaping)}")
    return config


def field_type(cls: type, name: str) -> Any:
    """The type of a field of a config dataclass, a dotted name reaching into nested configs."""
    head, _, rest = name.partition(".")
    hints = typing.get_type_hints(cls) if is_dataclass(cls) else {}
    if head not in hints:
        known = ", ".join(sorted(hints)) or "none"
        raise XvoeError(f"{cls.__name__} has no field {head!r} (its fields: {known})")
    if not rest:
        return hints[head]
    nested = _nested_dataclass(hints[head])
    if nested is None:
        raise XvoeError(f"{cls.__name__}.{head} is not a nested config")
    return field_type(nested, rest)


def split_assignment(text: str, flag: str) -> tuple[str, str]:
    """A command line's FIELD=VALUE as (FIELD, VALUE); `flag` names the option in the error."""
    name, equals, value = text.partition("=")
    if not equals or not name:
        raise XvoeError(f"{flag} takes FIELD=VALUE, not {text!r}")
    return name, value


def parse_value(kind: Any, text: str) -> Any:
    """A command-line string as a value of a config field's type (`none` for an optional one;
    a tuple as comma-separated items)."""
    if isinstance(kind, types.UnionType) or typing.get_origin(kind) is typing.Union:
        options = [a for a in typing.get_args(kind) if a is not type(None)]
        if text.lower() == "none" and len(options) < len(typing.get_args(kind)):
            return None
        if "," in text:     # several items: the tuple of a `float | tuple[float, ...]` field
            options = [a for a in options if typing.get_origin(a) is tuple] or options
        return parse_value(options[0], text)
    if typing.get_origin(kind) is tuple:
        item = typing.get_args(kind)[0] if typing.get_args(kind) else str
        return tuple(parse_value(item, part) for part in text.split(",") if part.strip())
    if kind is bool:
        if text.lower() in ("true", "yes", "1"):
            return True
        if text.lower() in ("false", "no", "0"):
            return False
        raise XvoeError(f"expected true or false, not {text!r}")
    if kind in (int, float, str):
        try:
            return kind(text)
        except ValueError:
            raise XvoeError(f"expected {'a whole number' if kind is int else 'a number'}, not {text!r}") from None
    raise XvoeError(f"a field of type {kind} cannot be set from the command line")
