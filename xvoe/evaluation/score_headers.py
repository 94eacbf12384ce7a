"""What a score file records of how it was made, in the header its curves file keeps
(`score_header`): the package version, the model and its identity, the split and where it was
read from, the score column, the aggregation, the surprise definitions and their settings, and
the digest of the scores it was written with; and the checks made against it (the curves of
these scores, this split, this model).
"""
from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import sys
import warnings
import zipfile
from pathlib import Path

import numpy as np

from ..errors import XvoeError
from ..fingerprints import arrays_hash, describe_split, file_hash
from ..models.config import from_dict, to_dict
from ..models.nll import InferenceConfig
from ..training.stages import PERCEPTION, PHYDNET
from .score_tables import scores_digest
from .scorer import Scorer
from .surprise import BETTER, PROPOSED

__all__ = ["UncheckedScores", "check_curves_of", "check_same_split", "check_scored_by", "curves_arrays",
           "header_of", "model_identity", "new_header", "package_version", "score_header", "scored_nll", "scored_split",
           "surprise_definitions", "warn_unchecked"]


def package_version() -> str:
    try:
        return importlib.metadata.version("xvoe")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def model_identity(scorer: Scorer) -> dict:
    """What a score file records of its model: a hash of its weights and configs (stable across
    machines, paths and what else the checkpoint holds: the run's xpl.pt and the shipped xpl hash
    alike), or for a model of your own its `module:name` and the hash of its source file."""
    found = {"source": scorer.source}
    if scorer.is_random:
        return found | {"seed": scorer.custom.seed}
    if scorer.custom is not None and scorer.phydnet is None:
        return found | _module_identity(scorer)
    modules = {PERCEPTION: scorer.vae, "dynamics": scorer.xpl, PHYDNET: scorer.phydnet}
    arrays = {f"{part}.{name}": tensor.detach().cpu().numpy() for part, module in modules.items() if module is not None
              for name, tensor in module.state_dict().items()}
    configs = {part: to_dict(module.config) for part, module in modules.items() if module is not None}
    return found | {"checkpoint_hash": arrays_hash(arrays, configs)}


def _module_identity(scorer: Scorer) -> dict:
    """A model of your own as `module:name` and the hash of the file that defines it."""
    if scorer.source is None:       # made in memory: its class names it
        kind = type(scorer.custom)
        where, name = kind.__module__, kind.__qualname__
        origin = getattr(sys.modules.get(where), "__file__", None)
    else:
        where, _, name = scorer.source.rpartition(":")
        origin = where if where.endswith(".py") else getattr(importlib.util.find_spec(where), "origin", None)
        where = Path(where).stem if where.endswith(".py") else where
    return {"module": f"{where}:{name}", "file_hash": file_hash(origin) if origin and Path(origin).is_file() else None}


def surprise_definitions(scorer: Scorer, how: str) -> dict:
    """The surprise definitions behind a score file's columns, with their settings (the NLL's
    settings are recorded beside them: `new_header`)."""
    if scorer.custom is not None:
        kept = " (in s_dyn)" if scorer.phydnet is not None else ""
        return {"own": f"the model's per-frame surprise{kept}, {how} over frames"}
    return {"mse": {"score": BETTER, "paper_score": PROPOSED, "aggregate": how}}


def new_header(scorer: Scorer, split: dict, data: str | Path, score_column: str, how: str,
               settings: dict | None = None) -> dict:
    """The header of a score file about to be written (`score_header` reads it back), with
    `model_settings`, where the model's settings came from (its checkpoints' recipes, and what the
    command line changed when they were trained: `checkpoint_settings`), for a model read from
    checkpoints; `settings`: what the NLL's columns were made with (xvoe.inference.score,
    `NLLRun.header`), where it has them. The digest of the scores is added once they are written."""
    found = {"xvoe": package_version(), "model": scorer.name, "model_identity": model_identity(scorer),
             "split": split, "data": str(Path(data).resolve()), "score": score_column, "aggregate": how,
             "surprise": surprise_definitions(scorer, how), **(settings or {})}
    if scorer.settings is not None:
        found["model_settings"] = scorer.settings
    return found


def curves_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of a curves file, read as numbers and text only (never unpickled), or a one-line error."""
    try:
        with np.load(path, allow_pickle=False) as saved:
            return {name: saved[name] for name in saved.files}
    except (OSError, ValueError, zipfile.BadZipFile) as error:
        raise XvoeError(f"{path} is not a curves file of xvoe score ({error})") from None


def score_header(path: str | Path, check: bool = True) -> dict:
    """What a score file was made with, kept in its curves file: the package version (`xvoe`),
    the model's name and identity (`model_identity`), the split's identity (`split`,
    `xvoe.fingerprints.split_identity`) and the path it was read from (`data`), the score column,
    the aggregation over frames, the surprise definitions (`surprise`), for the NLL its
    settings and seed (`nll`, `nll_seed`), and the digest of the scores it was written with
    (`scores_digest`). `check`: refuse, in one line, curves written with other scores
    (`check_curves_of`)."""
    curves = Path(path).with_suffix(".curves.npz")
    if not curves.is_file():
        raise XvoeError(f"{path} has no curves file beside it ({curves.name}), which holds its header")
    header = header_of(curves, curves_arrays(curves))
    if check:
        check_curves_of(path, curves, header)
    return header


def header_of(curves: Path, saved: dict[str, np.ndarray]) -> dict:
    """The header among the arrays of a curves file (`curves_arrays`), or a one-line error."""
    try:
        header = json.loads(str(saved["header"])) if "header" in saved else {}
    except ValueError:
        header = None
    if not isinstance(header, dict):
        raise XvoeError(f"{curves} is not a curves file of xvoe score (its header is not a JSON object)")
    return header


def check_curves_of(scores: str | Path, curves: str | Path, header: dict) -> None:
    """Refuse curves whose header records the digest of other scores than the file `scores`: the
    curves of another score file put beside it, or scores edited since they were written (a
    header that records none, an older xvoe's, is taken as it is)."""
    recorded = header.get("scores_digest")
    if recorded is not None and recorded != scores_digest(scores):
        raise XvoeError(f"{curves} was written with other scores than {scores} holds: the curves of another score "
                        f"file, or scores edited since (xvoe verify {scores} names the rows)")


class UncheckedScores(UserWarning):
    """A score file that records no split (made by hand, elsewhere, or by an older xvoe): it is
    read, but whether it belongs to the split cannot be checked (docs/decisions.md, "Score files
    that say what they are")."""


def scored_split(path: str | Path, header: dict | None = None) -> dict | None:
    """The identity of the split a score file was scored on (`xvoe.fingerprints.split_identity`), or
    None for a file that records none (`warn_unchecked` says so, once the file has been read).
    `header`: the file's, where the caller has read it (`score_header`)."""
    if header is None:
        header = score_header(path, check=False) if Path(path).with_suffix(".curves.npz").is_file() else {}
    return header.get("split")


def warn_unchecked(path: str | Path) -> None:
    """A warning for a score file that records no split, after it was read without a problem."""
    if scored_split(path) is None:
        warnings.warn(f"{path} does not record the split it was scored on, so it is not checked against one; "
                      "rescore it with this xvoe to have it checked", UncheckedScores, stacklevel=2)


def check_same_split(path: str | Path, identity: dict, data: str | Path, header: dict | None = None) -> None:
    """Refuse scores made on another split than `data`, whose identity is `identity`; `header`:
    the file's, where the caller has read it."""
    found = scored_split(path, header)
    if found is not None and found != identity:
        raise XvoeError(f"{path} was scored on another split ({describe_split(found)}) than {data} "
                        f"({describe_split(identity)}); score {data} instead")


def check_scored_by(path: str | Path, scorer: Scorer, header: dict | None = None) -> None:
    """Refuse a score file that another model made (its weights and configs, wherever they lie);
    `header`: the file's, where the caller has read it."""
    recorded = (header if header is not None else score_header(path, check=False)).get("model_identity")
    if recorded is None:
        raise XvoeError(f"{path} does not record the model it was made with: rescore it with this xvoe")
    loaded = model_identity(scorer)
    if _without_source(recorded) != _without_source(loaded):
        raise XvoeError(f"{path} was scored by another model than {scorer.name}: it names {_without_source(recorded)}, "
                        f"the model is {_without_source(loaded)}")


def _without_source(identity: dict) -> dict:
    return {key: value for key, value in identity.items() if key != "source"}


def scored_nll(path: str | Path, header: dict) -> InferenceConfig:
    """The NLL settings a score file was made with (its header's `nll`), to run the NLL again as
    it was run; one line where this xvoe no longer has one of them (a setting measurement
    retired), since its NLL cannot be made again."""
    try:
        return from_dict(InferenceConfig, header["nll"], "its NLL settings")
    except XvoeError as error:
        raise XvoeError(f"{path} was scored with NLL settings this xvoe cannot run ({error}); rescore it") from None
