"""Models shipped with the package: `xpl` (the default), `plato`, `xpl-noresidual`, `phydnet`.

They live in xvoe/weights/ as one run directory (a shared perception.pt and one checkpoint per
stage), written by `xvoe ship RUN_DIR` from a run of `xvoe pipeline`: weights and configs only,
without the optimiser state, so that they load with no download and stay small.
"""
from __future__ import annotations

import os
from pathlib import Path

import torch

from ..errors import XvoeError
from ..training.checkpoints import SHIPPED, WEIGHTS, load_checkpoint, shipped_path

BUDGET_BYTES = 25 * 2**20      # all shipped checkpoints together
KEPT = ("format", "stage", "step", "config", "model", "train", "meta")


def available_models() -> list[str]:
    return [name for name in SHIPPED if shipped_path(name)]


def ship(run_dir: str | os.PathLike, out: str | os.PathLike | None = None) -> list[Path]:
    """Copy the run's checkpoints into `out`, stripped to weights, config and step."""
    run_dir, out = Path(run_dir), Path(out or WEIGHTS)
    stages = [s for s in ("perception", *SHIPPED, "proposal") if (run_dir / f"{s}.pt").is_file()]
    if "perception" not in stages or "xpl" not in stages:
        raise XvoeError(f"{run_dir} holds no perception.pt and xpl.pt to ship")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for stage in stages:
        state = load_checkpoint(run_dir / f"{stage}.pt")
        slim = {key: state[key] for key in KEPT if key in state}
        slim["meta"] = {**slim.get("meta", {}), "shipped_from": str(run_dir.resolve())}
        target = out / f"{stage}.pt"
        partial = target.with_suffix(".pt.tmp")
        torch.save(slim, partial)
        os.replace(partial, target)
        written.append(target)
    total = sum(p.stat().st_size for p in out.glob("*.pt"))
    if total > BUDGET_BYTES:
        raise XvoeError(f"shipped checkpoints take {total / 2**20:.1f} MB, "
                        f"over the {BUDGET_BYTES / 2**20:.0f} MB budget")
    return written
