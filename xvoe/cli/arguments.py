"""What every verb's parser is built from: the parser class, the argument types that refuse a bad
value in one line before any work, the name lists its help takes from the registries, and the
check of the paths a command reads and writes.

Nothing here imports torch (nor h5py or pymunk): `xvoe --help` builds every verb's parser. What
a verb needs of the heavier layers is imported inside the function that runs it, or that parses
a value."""
from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import xvoe

from ..domains import DEVICES, Domain, check_number
from ..errors import XvoeError
from ..models.config import parse_field, parse_value
from ..outputs import refuse_overlap
from ..processes import interrupts_held
from ..resources import cores
from ..training.config import DEFAULT_RECIPE, RECIPE_NAMES
from ..training.stages import RANDOM, SCORED, STAGES

__all__ = ["Parser", "Writes", "add_device", "argument", "check_paths", "default_workers", "field", "flag",
           "generate_field", "latent_stages", "listed", "output_of", "positive", "recipe_names", "scored_by_surprise",
           "scored_checkpoints", "shard"]


class Parser(argparse.ArgumentParser):
    """argparse, but a bad argument gives one line (and exit code 2), not the whole usage."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # a value such as -1/2 (for --shard) is a value to check, not an unknown option
        self._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-\d+/\d+$")

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# --- argument types: each refuses a bad value in one line, before any work ------------------

def shard(text: str) -> tuple[int, int]:
    try:
        index, count = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N (part I of N, counted from 0), not {text!r}") from None
    if not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"expected I/N with 0 <= I < N, not {text!r}")
    return index, count


def positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, not {value}")
    return value


def argument(parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """An argparse type that refuses, in one line, what `parse` refuses: before any work."""
    def checked(text: str) -> Any:
        try:
            return parse(text)
        except XvoeError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    return checked


def flag(kind: type, domain: Domain, name: str) -> Callable[[str], Any]:
    """The argparse type of a flag of no config field: a `kind` in `domain`, refused naming `name`."""
    return argument(lambda text: check_number(domain, name, parse_value(kind, text)))


def field(cls: type, name: str) -> Callable[[str], Any]:
    """The argparse type of a flag that sets field `name` of config `cls`: its type and declared domain."""
    return argument(lambda text: parse_field(cls, name, text))


def generate_field(name: str) -> Callable[[str], Any]:
    """`field` of GenerateConfig, whose module (h5py, pymunk) loads when a value is parsed, not for --help."""
    return argument(lambda text: parse_field(xvoe.GenerateConfig, name, text))


def _device(text: str) -> str:
    with interrupts_held():     # imported here, not for --help: a Ctrl-C inside torch's import aborts the process
        from ..models.devices import parse_device
    return str(parse_device(text))


def add_device(parser: argparse.ArgumentParser, what: str) -> None:
    # a device name is checked here; whether this machine has it, first thing in `main`
    parser.add_argument("--device", type=argument(_device), default="cpu",
                        help=f"where {what} runs: {DEVICES} (default cpu)")


def default_workers() -> int:
    return min(8, cores())


# --- names for the help, from the registries (each written once, there) ---------------------

def recipe_names() -> str:
    """The recipes for a --help line, the default (the shipped models') named first."""
    others = [name for name in RECIPE_NAMES if name != DEFAULT_RECIPE]
    return f"{DEFAULT_RECIPE} (default, the shipped models'), " + ", ".join(others)


def scored_checkpoints() -> str:
    """The stage checkpoints `--model` takes, as a --help list: xpl.pt, plato.pt, ..."""
    return ", ".join(STAGES[name].checkpoint for name in SCORED)


def listed(names: Iterable[str], last: str = "and") -> str:
    """Names for a --help line or a message: a, b and c (or a, b or c)."""
    *others, final = names
    return f"{', '.join(others)} {last} {final}" if others else final


def latent_stages() -> str:
    """The stages that train on the perception's latent cache, for a --help line: a, b and c."""
    return listed(name for name, entry in STAGES.items() if entry.reads_latents)


def scored_by_surprise() -> str:
    """The shipped models scored through `surprise(videos)` as a model of your own is (the harness
    checks them, within the time limit): those outside the XPL family, and chance."""
    return listed([*(name for name in SCORED if not STAGES[name].variant), RANDOM], "or")


# --- the paths a command names: no output may be one of its inputs --------------------------

@dataclass(frozen=True)
class Writes:
    """What a verb that writes a file names: the arguments it reads, the one it writes, and the
    suffixes of what it writes; set beside its parser (`set_defaults(writes=...)`)."""

    reads: tuple[str, ...]
    out: str
    suffixes: tuple[str, ...]
    # what it writes when its output argument is left out
    default: Callable[[argparse.Namespace], Path] | None = None
    # what it writes besides its main output, where the argument is given: (argument, suffixes)
    also: tuple[tuple[str, tuple[str, ...]], ...] = ()


def output_of(args: argparse.Namespace) -> str | Path | None:
    """The file a verb writes: its output argument, or where the verb writes without one."""
    output = getattr(args, args.writes.out)
    return output if output is not None or args.writes.default is None else args.writes.default(args)


def check_paths(args: argparse.Namespace) -> None:
    """The one check of a command's paths before any work: no output, given or by default, may
    be one of its inputs."""
    writes = args.writes
    if writes is None:
        return
    inputs = []
    for name in writes.reads:
        value = getattr(args, name)
        inputs += value if isinstance(value, list) else [value] if value else []
    for name, written in writes.also:
        if getattr(args, name) is not None:
            refuse_overlap(inputs, getattr(args, name), written, what=f"--{name}")
    output = output_of(args)
    if output is None:
        return
    given = getattr(args, writes.out) is not None
    refuse_overlap(inputs, output, writes.suffixes, what=f"--{writes.out}" if given else f"the default --{writes.out}")
