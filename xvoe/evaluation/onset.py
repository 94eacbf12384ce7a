"""Violation onset: is the model surprised at the right moment? The impossible member's per-frame
surprise against the possible one's, around the frame where the event happens."""
from __future__ import annotations

import numpy as np

from .metrics import scenario_settings, share_of

__all__ = ["ONSET_FIELDS", "ONSET_SHARE", "onset", "onset_pairs"]

ONSET_SHARE = 0.1       # of the peak difference: where the surprise "rises"
ONSET_FIELDS = ("model", "surprise", "scenario", "setting", "pairs", "timely", "timely_low", "timely_high",
                "median_peak_offset")


def onset_pairs(scores: dict[str, np.ndarray], per_frame: np.ndarray, event_frame: np.ndarray) -> list[dict]:
    """For every S1/S3 pair with an event frame: the impossible member's per-frame surprise less
    the possible one's (rows of `per_frame` (N, T) follow the scores' rows; `event_frame` by
    row too); `timely`, whether that difference first rises above a tenth of its peak at or
    after the event frame; `peak_offset`, how many frames after it the difference peaks
    (negative: before)."""
    found = []
    for scenario, setting in scenario_settings(scores):
        if setting not in ("S1", "S3"):
            continue
        mask = (scores["scenario"] == scenario) & (scores["setting"] == setting)
        rows = np.flatnonzero(mask)
        by_pair: dict[int, dict[bool, int]] = {}
        for row in rows:
            by_pair.setdefault(int(scores["pair"][row]), {})[bool(scores["possible"][row])] = row
        for pair, members in sorted(by_pair.items()):
            if set(members) != {True, False} or event_frame[members[False]] < 0:
                continue
            event = int(event_frame[members[False]])
            difference = per_frame[members[False]] - per_frame[members[True]]
            # a rise is a tenth of the peak: a model that reads the whole video (as Transformer 1
            # does) differs a little before the event in every pair, which is no verdict
            positive = np.flatnonzero(difference > ONSET_SHARE * difference.max()) if difference.max() > 0 \
                else np.array([], dtype=int)
            found.append({"scenario": scenario, "setting": setting, "pair": pair, "event_frame": event,
                          "first_positive": int(positive[0]) if len(positive) else -1,
                          "timely": bool(len(positive) and positive[0] >= event),
                          "peak_offset": int(np.argmax(difference)) - event})
    return found


def onset(scores: dict[str, np.ndarray], per_frame: np.ndarray, event_frame: np.ndarray, model: str,
          rounds: int = 1000, seed: int = 0, surprise: str = "mse") -> list[dict]:
    """Per S1/S3 setting: the share of pairs whose surprise rises at or after the event (with a
    Wilson interval over pairs) and the median frame of its peak after the event. surprise:
    the definition whose curves `per_frame` are ("mse": s_img + s_dyn; "nll": -log p(x_t | x_<t))."""
    pairs = onset_pairs(scores, per_frame, event_frame)
    rows = []
    for scenario, setting in dict.fromkeys((p["scenario"], p["setting"]) for p in pairs):
        chosen = [p for p in pairs if (p["scenario"], p["setting"]) == (scenario, setting)]
        timely = np.array([p["timely"] for p in chosen], dtype=float)
        estimate = share_of(timely)
        rows.append(dict(zip(ONSET_FIELDS, (model, surprise, scenario, setting, len(chosen), estimate.value,
                                            estimate.low, estimate.high,
                                            float(np.median([p["peak_offset"] for p in chosen]))))))
    return rows
