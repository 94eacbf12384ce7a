"""Models shipped with the package: every scored stage's (`SHIPPED`), `xpl` the default.

They live in xvoe/weights/ as one run directory (a shared perception.pt and one checkpoint per
stage), written by `xvoe ship RUN_DIR` from a run of `xvoe pipeline`: weights and configs only,
without the optimiser state, so that they load with no download and stay small. Only a run
its recipe made as written is shipped, so that one command makes each shipped model again.
"""
from __future__ import annotations

import io
import os
from pathlib import Path

import torch

from ..errors import XvoeError
from ..outputs import atomic_paths, claim_directory
from ..training.checkpoints import SHIPPED, WEIGHTS, load_checkpoint, shipped_path
from ..training.provenance import recipe_differences
from ..training.stages import PERCEPTION, STAGES

__all__ = ["BUDGET_BYTES", "KEPT", "available_models", "ship"]

BUDGET_BYTES = 25 * 2**20      # all shipped checkpoints together
KEPT = ("format", "stage", "step", "config", "model", "train", "meta")
# the shipped models that read the shared perception's latents
READS_PERCEPTION = tuple(name for name, entry in STAGES.items() if entry.reads_latents)


def available_models() -> list[str]:
    return [name for name in SHIPPED if shipped_path(name)]


def ship(run_dir: str | os.PathLike, out: str | os.PathLike | None = None) -> list[Path]:
    """Copy the run's checkpoints into `out`, stripped to weights, config and step: every one
    or none (each is read and the budget checked before any is written). The paths of the
    machine it was trained on stay behind."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise XvoeError(f"{run_dir}: no such run directory")
    stages = [name for name, entry in STAGES.items() if (run_dir / entry.checkpoint).is_file()]
    if not stages:
        readers = " or ".join(STAGES[s].checkpoint for s in READS_PERCEPTION if STAGES[s].scored)
        others = ", ".join(entry.checkpoint for name, entry in STAGES.items()
                           if entry.scored and name not in READS_PERCEPTION)
        raise XvoeError(f"{run_dir} holds no checkpoint to ship ({STAGES[PERCEPTION].checkpoint} with {readers}, "
                        f"or {others})")
    if PERCEPTION not in stages and (readers := [s for s in stages if s in READS_PERCEPTION]):
        raise XvoeError(f"{run_dir} holds no {STAGES[PERCEPTION].checkpoint}, whose latents its {', '.join(readers)} "
                        "read; nothing was written")
    claim_directory(out or WEIGHTS, make=False)
    states = {stage: load_checkpoint(run_dir / STAGES[stage].checkpoint, stage) for stage in stages}
    for stage, state in states.items():
        if differences := recipe_differences(state):
            raise XvoeError(f"{run_dir / STAGES[stage].checkpoint} is not what its recipe makes "
                            f"({'; '.join(differences[:3])}); ship runs of `xvoe pipeline --recipe NAME` as written; "
                            "nothing was written")
    if PERCEPTION in states:      # PhyDNet reads pixels: it ships on its own
        _check_shared_perception(states[PERCEPTION], Path(out or WEIGHTS), set(stages))
    slim = {stage: _slim(state, run_dir.name) for stage, state in states.items()}
    kept = sum(p.stat().st_size for p in Path(out or WEIGHTS).glob("*.pt") if p.stem not in slim)
    total = kept + sum(len(data) for data in slim.values())
    if total > BUDGET_BYTES:
        raise XvoeError(f"shipped checkpoints would take {total / 2**20:.1f} MB, "
                        f"over the {BUDGET_BYTES / 2**20:.0f} MB budget; nothing was written")
    out = claim_directory(out or WEIGHTS)
    targets = [out / STAGES[stage].checkpoint for stage in slim]
    with atomic_paths(*targets) as temporaries:
        for temporary, data in zip(temporaries, slim.values()):
            temporary.write_bytes(data)
    return targets


def _check_shared_perception(perception: dict, out: Path, shipping: set[str]) -> None:
    """A new perception.pt changes the latents that every XPL-family model there was trained on:
    those left behind would read latents they never saw."""
    current = out / STAGES[PERCEPTION].checkpoint
    if not current.is_file():
        return
    old = load_checkpoint(current)["model"]
    if old.keys() == perception["model"].keys() and all(torch.equal(old[k], perception["model"][k]) for k in old):
        return
    stranded = [STAGES[s].checkpoint for s in READS_PERCEPTION if (out / STAGES[s].checkpoint).is_file()
                and s not in shipping]
    if stranded:
        raise XvoeError(f"the run's {current.name} is not the shipped one, which {', '.join(stranded)} read; ship a "
                        "run that trained them on its perception too; nothing was written")


def _slim(state: dict, run_name: str) -> bytes:
    """A checkpoint's weights, config and step, serialised; its meta without absolute paths."""
    slim = {key: state[key] for key in KEPT if key in state}
    meta = {k: v for k, v in slim.get("meta", {}).items() if not (isinstance(v, str) and os.path.isabs(v))}
    slim["meta"] = meta | {"shipped_from": run_name}
    buffer = io.BytesIO()
    torch.save(slim, buffer)
    return buffer.getvalue()
