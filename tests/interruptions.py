"""Interruptions at random moments leave nothing broken.

Each command below (generate in workers, encode, score in two workers, a tiny training run,
metrics) runs once whole, for its outputs and its time; then, N times for each signal, it is
started again in a folder of its own and sent SIGKILL (to the command's process alone, as the
out-of-memory killer or `kill -9` would) or SIGINT (to its process group, as Ctrl-C in a
terminal) after a delay drawn (seeded) between the interpreter's start and that time. A trial
whose command ended before its signal is checked too but not counted: the moment is drawn again,
within the shortest run seen so far, until N trials really interrupted the command (at most 4N
draws). Each trial checks:

- no process of the run is left (its process group is empty within 20 s);
- no broken file under a final name: each output is absent or the same bytes as the whole
  run's (a training run: its checkpoint loads and its loss CSV ends at the checkpoint's step);
- a Ctrl-C ends the command with exit code 130 (or 0 where it had finished) and at most one
  line on stderr, no traceback;
- the rerun (the same command with --overwrite; a training run with --resume) gives the same
  bytes as the whole run (a training run: the same weights and losses; its time columns
  differ) and leaves nothing else in the folder: no temporary, claim or parts folder.

Run by hand: python tests/interruptions.py WORKDIR [--times N] [--seed S] [--commands a,b];
it prints one JSON line per command with its counts and exits 1 if any check failed.
tests/test_interruptions.py runs it once per signal and command.
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

XVOE = [sys.executable, "-m", "xvoe"]
SIGNALS = {"SIGKILL": signal.SIGKILL, "SIGINT": signal.SIGINT}
# seconds before the interpreter runs a line of xvoe (`python -c pass` takes 0.07 s): a Ctrl-C
# sooner meets Python's own start-up, whose traceback no code of the project can replace
STARTING = 0.15
TIME_COLUMNS = ("minutes", "items_per_second")      # a training log's columns that are the clock's


@dataclass
class Command:
    """A command run in a folder of its own (`{out}`), its outputs found there."""

    name: str
    args: list[str]                     # with {out} for the folder and {inputs} for the shared inputs
    rerun: str = "--overwrite"          # what the rerun adds
    copies: tuple[str, ...] = ()        # inputs copied into the folder first (a split whose cache is written beside it)
    trained: bool = False               # outputs compared by weights and losses, not bytes


def commands(workers: int) -> list[Command]:
    return [
        Command("generate", ["generate", "--split", "train", "--videos", "24", "--size", "32", "--workers",
                             str(workers), "--out", "{out}/g.h5", "--quiet"]),
        Command("encode", ["encode", "--model", "xpl", "--data", "{inputs}/train.h5", "--out", "{out}/run", "--quiet"]),
        Command("score", ["score", "--model", "xpl", "--data", "{out}/test.h5", "--out", "{out}/s.csv", "--workers",
                          str(workers), "--quiet"], copies=("test.h5",)),
        Command("train", ["train", "perception", "--data", "{inputs}/train.h5", "--out", "{out}/run", "--steps", "4",
                          "--batch-size", "4", "--set", "log_every=1", "--set", "checkpoint_minutes=0.002",
                          "--set", "model.latent_dim=8", "--set", "model.cnn_hidden=16", "--quiet"],
                rerun="--resume", trained=True),
        Command("metrics", ["metrics", "{inputs}/s.csv", "--rounds", "50", "--out", "{out}/r"]),
    ]


def make_inputs(inputs: Path) -> None:
    """A small training split, a test split and its random model's scores."""
    inputs.mkdir(parents=True, exist_ok=True)
    steps = [["generate", "--split", "train", "--videos", "16", "--size", "32", "--out", f"{inputs}/train.h5"],
             ["generate", "--split", "test", "--pairs", "1", "--size", "32", "--out", f"{inputs}/test.h5"],
             ["score", "--model", "random", "--data", f"{inputs}/test.h5", "--out", f"{inputs}/s.csv"]]
    for step in steps:
        if not Path(step[step.index("--out") + 1]).exists():
            subprocess.run(XVOE + step + ["--quiet"], check=True, stdout=subprocess.DEVNULL)


def argv(command: Command, out: Path, inputs: Path) -> list[str]:
    return XVOE + [arg.format(out=out, inputs=inputs) for arg in command.args]


def prepare(command: Command, out: Path, inputs: Path) -> None:
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    for name in command.copies:
        shutil.copy(inputs / name, out / name)


def contents(folder: Path, command: Command) -> dict[str, str]:
    """Every file under `folder` (hidden ones too) but the copied inputs: its digest, or for a
    training run's checkpoint and log, their weights and losses."""
    found = {}
    for path in sorted(folder.rglob("*")):
        name = str(path.relative_to(folder))
        if path.is_dir() or name in command.copies:
            continue
        found[name] = trained_digest(path) if command.trained else hashlib.sha256(path.read_bytes()).hexdigest()
    return found


def trained_digest(path: Path) -> str:
    """A checkpoint's step and weights, a loss log's rows without the clock's columns."""
    if path.suffix == ".pt":
        from xvoe.fingerprints import arrays_hash
        from xvoe.training.checkpoints import load_checkpoint

        state = load_checkpoint(path)
        return f"step {state['step']} " + arrays_hash({k: v.numpy() for k, v in state["model"].items()}, {})
    if path.suffix == ".csv":
        with open(path, newline="") as handle:
            rows = [{k: v for k, v in row.items() if k not in TIME_COLUMNS} for row in csv.DictReader(handle)]
        return hashlib.sha256(json.dumps(rows).encode()).hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


def group_members(group: int) -> list[int]:
    """The running processes (not zombies) of process group `group`."""
    found = []
    for entry in Path("/proc").iterdir():
        with contextlib.suppress(OSError, IndexError, ValueError):
            if entry.name.isdigit():
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                if fields[0] != "Z" and int(fields[2]) == group:
                    found.append(int(entry.name))
    return found


def left_behind(group: int, wait: float = 20.0) -> list[int]:
    deadline = time.monotonic() + wait
    while (members := group_members(group)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return members


def run_whole(command: Command, out: Path, inputs: Path) -> tuple[float, dict[str, str]]:
    """The command uninterrupted, in the folder the trials use (outputs record where they were made)."""
    prepare(command, out, inputs)
    began = time.monotonic()
    subprocess.run(argv(command, out, inputs), check=True, stdout=subprocess.DEVNULL)
    return time.monotonic() - began, contents(out, command)


def partial_problems(command: Command, out: Path, whole: dict[str, str]) -> list[str]:
    """What an interrupted run left broken under a final name."""
    problems = []
    for path in sorted(out.rglob("*")):
        name = str(path.relative_to(out))
        if path.is_dir() or name in command.copies or any(part.startswith(".") for part in Path(name).parts):
            continue        # hidden, or in a hidden folder: a temporary or claim, which the next run removes
        if command.trained:
            problems += trained_problems(path)
        elif name not in whole or hashlib.sha256(path.read_bytes()).hexdigest() != whole[name]:
            problems.append(f"{name} differs from the whole run's")
    return problems


def trained_problems(path: Path) -> list[str]:
    from xvoe.errors import XvoeError
    from xvoe.training.checkpoints import load_checkpoint

    if path.suffix != ".pt":
        return []
    try:
        step = load_checkpoint(path)["step"]
    except XvoeError as error:
        return [f"{path.name} does not load: {error}"]
    log = path.with_suffix(".csv")
    if not log.exists():
        return [f"{path.name} of step {step} has no loss log"]
    with open(log, newline="") as handle:
        steps = [int(row["step"]) for row in csv.DictReader(handle)]
    return [] if steps and steps[-1] == step else [f"{log.name} ends at step {steps[-1:]}, its checkpoint at {step}"]


@dataclass
class Tally:
    trials: int = 0                     # runs that the signal really interrupted
    finished_first: int = 0             # draws whose signal came after the command had ended
    shortest: float = float("inf")      # the quickest of those runs, in seconds: later moments fall within it
    problems: list[str] = field(default_factory=list)


def trial(command: Command, how: str, delay: float, out: Path, inputs: Path, whole: dict[str, str],
          tally: Tally) -> None:
    prepare(command, out, inputs)
    began = time.monotonic()
    process = subprocess.Popen(argv(command, out, inputs), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(delay)
    finished = process.poll() is not None
    if finished:
        tally.shortest = min(tally.shortest, time.monotonic() - began)
    if not finished:
        if how == "SIGKILL":
            process.kill()
        else:
            os.killpg(process.pid, signal.SIGINT)
    _, err = process.communicate()
    said = f"{command.name} {how} at {delay:.2f} s"
    tally.trials += not finished
    tally.finished_first += finished
    if stray := left_behind(process.pid):
        tally.problems.append(f"{said}: processes {stray} left running")
        for pid in stray:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    # killed by the SIGINT itself (-2) is what a shell reports as 130 too: CPython ends so where a
    # Ctrl-C met C code that runs Python source (as torch's import does), even once it was handled
    if how == "SIGINT" and (process.returncode not in (0, 130, -signal.SIGINT) or len(err.splitlines()) > 1):
        tally.problems.append(f"{said}: exit {process.returncode}, {err.strip()[-300:]!r}")
    tally.problems += [f"{said}: {problem}" for problem in partial_problems(command, out, whole)]
    if finished and process.returncode == 0 and contents(out, command) == whole:
        return
    rerun = subprocess.run(argv(command, out, inputs) + [command.rerun], stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, text=True)
    if rerun.returncode != 0:
        tally.problems.append(f"{said}: the rerun failed: {rerun.stderr.strip()[-300:]!r}")
    elif (found := contents(out, command)) != whole:
        extra = sorted(set(found) ^ set(whole)) or sorted(k for k in found if found[k] != whole[k])
        tally.problems.append(f"{said}: the rerun differs from the whole run: {extra}")


def main(argv_: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workdir", type=Path)
    parser.add_argument("--times", type=int, default=20,
                        help="trials that really interrupted the command, for each signal and command")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--commands", default="generate,encode,score,train,metrics")
    parser.add_argument("--signals", default=",".join(SIGNALS), help="of SIGKILL and SIGINT")
    args = parser.parse_args(argv_)
    workers = min(2, len(os.sched_getaffinity(0)))
    inputs = args.workdir / "inputs"
    make_inputs(inputs)
    rng = random.Random(args.seed)
    failed = False
    for command in (c for c in commands(workers) if c.name in args.commands.split(",")):
        took, whole = run_whole(command, args.workdir / command.name, inputs)
        tallies = {how: Tally() for how in SIGNALS if how in args.signals.split(",")}
        for how, tally in tallies.items():
            for _ in range(4 * args.times):
                if tally.trials == args.times:
                    break
                latest = max(min(took, tally.shortest) - 0.05, STARTING)
                trial(command, how, rng.uniform(STARTING, latest), args.workdir / command.name, inputs, whole, tally)
        report = {"command": command.name, "whole_seconds": round(took, 1),
                  **{how: {"trials": t.trials, "finished_first": t.finished_first, "problems": t.problems}
                     for how, t in tallies.items()}}
        print(json.dumps(report), flush=True)
        failed |= any(t.problems for t in tallies.values())
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
