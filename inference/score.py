"""The NLL columns of a score file: -log p(video) under the Pyro model, its ESS, p(hidden
object), p(two identical objects), and the NLL less that of a reference drawing only what was
seen; the settings they are made with (`nll_run`) and where each came from."""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from torch import Tensor

from xvoe.domains import check_config
from xvoe.errors import XvoeError
from xvoe.evaluation.scorer import Scorer
from xvoe.evaluation.surprise import DrawnScene
from xvoe.models.config import field_type, parse_field, split_assignment, to_dict

from .model import InferenceConfig, pixel_log_normaliser
from .surprise import NLLSurprise, check_particles, drawn_surprise

__all__ = ["NLLRun", "nll_batch", "nll_config", "nll_defaults_note", "nll_excess", "nll_run", "nll_settings",
           "nll_sources", "reference_nll", "under_prior_two", "xpl_nll"]


def nll_config(base: InferenceConfig, particles: int | None = None,
               settings: dict[str, Any] | None = None) -> InferenceConfig:
    """The NLL's settings: `base` (the model's) with `particles` (None: its own) and the fields
    in `settings` changed; a name it has no field of is an error that lists its fields."""
    settings = dict(settings or {})
    for name in settings:
        field_type(InferenceConfig, name)
    if "particles" in settings and particles is not None and settings["particles"] != particles:
        raise XvoeError("give the particles once: as particles, or in the NLL settings")
    return check_config(replace(base, **({"particles": particles} if particles is not None else {}), **settings))


def nll_settings(assignments: list[str]) -> dict[str, Any]:
    """`--nll-set FIELD=VALUE` lines as typed InferenceConfig fields."""
    settings = {}
    for text in assignments:
        name, value = split_assignment(text, "--nll-set")
        settings[name] = parse_field(InferenceConfig, name, value)
    return settings


def reference_nll(s_rec: np.ndarray, pixels: int, sigma: float) -> np.ndarray:
    """-log N(frames | the perception's drawing of what it saw, sigma^2) per video, from its
    s_rec curve (N, T) and the pixels of one frame: the NLL of a reference that draws the seen
    objects and nothing else, under the Pyro model's pixel likelihood. The NLL less this is a
    log-likelihood ratio (nll_excess): the pixels of the seen objects that the perception
    misses, the same under every hypothesis, cancel, as in the excess score."""
    return s_rec.sum(axis=1) / (2 * sigma ** 2) + pixel_log_normaliser(pixels * s_rec.shape[1], sigma)


def under_prior_two(scores: dict[str, np.ndarray], used: float, prior: float) -> dict[str, np.ndarray]:
    """A score table's NLL columns (nll, p_two, nll_excess) as they would be under another prior
    of two identical objects, from the one scored with `used`: the file's p(x) and p_two give
    p(x | one) and p(x | two) (posterior odds are prior odds times the Bayes factor), and p(x) =
    (1 - prior) p(x | one) + prior p(x | two). Videos with no second explanation (p_two 0) keep
    theirs. Exact where the SMC's pilot stops the same videos: it compares the hidden-object
    branch with the sum of those without one, which the prior moves by at most log(prior /
    used) nats. `prior` 0 leaves the one-object explanation alone: where p_two rounded to 1, whose
    p(x | one) underflowed, that is an infinite NLL."""
    if not 0 < used < 1 or not 0 <= prior < 1:
        raise XvoeError(f"priors of two objects lie in [0, 1) (the scored one in (0, 1)), not {used} and {prior}")
    log_x, p_two = -scores["nll"].astype(np.float64), scores["p_two"].astype(np.float64)
    gap = p_two > 0
    with np.errstate(divide="ignore", invalid="ignore"):   # prior 0: log 0 = -inf leaves the one-object term alone
        one = log_x + np.log1p(-p_two) - np.log1p(-used)          # log p(x | one)
        two = log_x + np.log(np.where(gap, p_two, 1.0)) - np.log(used)
        log_new = np.where(gap, np.logaddexp(one + np.log1p(-prior), two + np.log(prior)), log_x)
        p_new = np.where(gap & (prior > 0), np.exp(two + np.log(prior) - log_new), 0.0)
    return {**scores, "nll": -log_new, "p_two": p_new, "nll_excess": scores["nll_excess"] - log_new - scores["nll"]}


def xpl_nll(scorer: Scorer, batch: dict[str, Tensor], config: InferenceConfig, seed: int,
            drawn: DrawnScene) -> list[NLLSurprise]:
    """The NLL surprise of each encoded video (`encode_videos`) under the Pyro hidden-object model,
    each from a generator of its own seeded from `seed` and its pixels (`video_seed`), so that a
    video's score hangs neither on the others' nor on where it sits in the split; `drawn`: the
    batch as the MSE score drew it (`xvoe.evaluation.surprise.draw_scene`)."""
    return [drawn_surprise(scorer.vae, scorer.xpl, batch["frames"][i], batch["visible"][i], batch["occluder"][i],
                           drawn.video(i), config, seed=seed)
            for i in range(len(batch["mean"]))]


_FALLBACKS = {"recipe": "its recipe's", "defaults": "InferenceConfig's defaults"}


def nll_sources(origin: str, overridden: set[str]) -> dict[str, str]:
    """Where each NLL setting came from, for a score file's header: "command line" for those
    overridden (`--particles`, `--nll-set`, or `score`'s particles and nll_settings), else the
    model's `origin`: "checkpoint" where it stores its settings, else "recipe" or "defaults"."""
    return {f.name: "command line" if f.name in overridden else origin for f in fields(InferenceConfig)}


def nll_defaults_note(header: dict) -> str | None:
    """One line saying which NLL settings a score file's model took from its recipe (or, with no
    recipe this xvoe knows, InferenceConfig's defaults) because its checkpoint stores none (one
    made before they were stored), or None: what `xvoe score` prints after such a run; from
    Python the header's `nll_source` says it."""
    sources = header.get("nll_source") or {}
    fallback = next((where for where in _FALLBACKS if where in sources.values()), None)
    if fallback is None:        # a run that sets every field (xvoe verify) takes none
        return None
    given = sorted(name for name, where in sources.items() if where == "command line")
    given_text = f", {' and '.join(given)} from the command line" if given else ""
    return (f"{header['model']} stores no NLL settings; scored with {_FALLBACKS[fallback]}{given_text}: "
            + " ".join(f"{name}={_typed(value)}" for name, value in header["nll"].items()))


def _typed(value: Any) -> str:
    """A setting as `--nll-set` takes it (a tuple's items joined by commas)."""
    return ",".join(map(str, value)) if isinstance(value, (tuple, list)) else str(value)


@dataclass(frozen=True)
class NLLRun:
    """What a score's NLL columns are made with (`nll_run`): the settings, where each came from
    (`nll_sources`), and the seed of the draws (each video's from a generator of its own)."""

    config: InferenceConfig
    sources: dict[str, str]
    seed: int = 0

    def header(self) -> dict:
        """The score file header's record of them (xvoe.evaluation.score_headers, `new_header`)."""
        return {"nll": to_dict(self.config), "nll_source": self.sources, "nll_seed": self.seed}


def nll_run(scorer: Scorer, particles: int | None = None, seed: int = 0,
            settings: dict[str, Any] | None = None) -> NLLRun:
    """The model's own NLL settings (its checkpoint's; where it stores none, its recipe's, which
    the header records and `nll_defaults_note` words), each changed where this
    run overrides it (`particles`, `settings`); a one-line error for a model without reasoning."""
    if scorer.xpl is None or not scorer.xpl.config.use_reasoning:
        raise XvoeError(f"the NLL surprise needs an XPL model with reasoning; {scorer.name} has none")
    config = nll_config(scorer.nll or InferenceConfig(), particles, settings)
    check_particles(config.particles)
    overridden = set(settings or ()) | ({"particles"} if particles is not None else set())
    return NLLRun(config, nll_sources(scorer.nll_origin, overridden), seed)


def nll_batch(scorer: Scorer, batch: dict[str, Tensor], run: NLLRun,
              drawn: DrawnScene) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The NLL's columns of encoded videos (`encode_videos`), (B,) each: nll, -log p(video) under
    the Pyro model, its ess, p_hidden and p_two; and its curve nll (B, T), -log p(x_t | x_<t)
    (the SMC's; importance sampling keeps none). `drawn`: the batch as the MSE score drew it."""
    found = xpl_nll(scorer, batch, run.config, run.seed, drawn)
    columns = {name: np.array([getattr(f, name) for f in found], dtype=float)
               for name in ("nll", "ess", "p_hidden", "p_two")}
    curves = {"nll": np.stack([f.frame_nll.numpy() for f in found])} if run.config.method == "smc" else {}
    return columns, curves


def nll_excess(nll: np.ndarray, s_rec: np.ndarray, size: int, run: NLLRun) -> np.ndarray:
    """The column nll_excess (N,): the NLL less that of a reference drawing only what was seen
    (`reference_nll`), from the MSE score's s_rec curve (N, T) of frames of `size` pixels a side."""
    return nll - reference_nll(s_rec, 4 * size * size, run.config.pixel_sigma)
