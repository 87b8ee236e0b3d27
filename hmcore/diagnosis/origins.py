"""A later origin: when a diagnosis accepts nothing while its calibrated model misses the
held-back history beyond noise, something acts late in the record (water arriving, a barrier
reached, a well damaged). The diagnosis takes its own advice and diagnoses again with the
fitted window ending later - a rolling origin, in time order - and says which window named
the cause.

``DiagnosisSettings.later_origins`` are the ends of the later fitted windows, as fractions of
the record (first to last observed day); the first that lies beyond the current end and
leaves at least ``later_min_heldout`` measured points to hold back is used, then the next
beyond that one while no window names a cause (:func:`hmcore.diagnosis.rounds.diagnose_all`
runs them). Each later window
starts from the calibrated values of the earlier one (polished on the longer record) and is
judged by the same rules on its own held-back data. Plain functions; nothing here simulates.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from hmcore.model.case import Case
from hmcore.diagnosis.settings import DiagnosisSettings


def later_origin(case: Case, doc: dict, s: DiagnosisSettings) -> float | str:
    """The end of the next fitted window (days), or why there is none (a sentence)."""
    if doc.get("accepted"):
        return "a cause was accepted"
    if doc.get("heldout_within_noise", True):
        return "the calibrated model fits the held-back history within noise"
    days = case.informative.days.to_numpy(float)
    if days.size == 0 or not s.later_origins:
        return "no later origin is set (later_origins)"
    d0, d1 = float(days.min()), float(days.max())
    end = float(doc["history_end_days"])
    for frac in s.later_origins:
        t = float(d0 + frac * (d1 - d0))
        if t <= end + 1e-6:
            continue
        if int(np.count_nonzero(days > t)) >= s.later_min_heldout:
            return t
    return (f"no later origin in {list(s.later_origins)} of the record leaves "
            f"{s.later_min_heldout} points to hold back")


def later_case(case: Case, origin: float) -> Case:
    """The case fitted up to ``origin`` (days), later data held back."""
    return dataclasses.replace(case, history_end_days=float(origin))


def combine(docs: list[dict]) -> tuple[dict, bool]:
    """The diagnosis of every window, in time order, and whether the last named the answer
    (its document is then the answer, with the earlier windows summarised; otherwise the
    first window's, with what each later one found)."""
    windows = [_window(d) for d in docs]
    ends = [d["history_end_days"] for d in docs]
    last = docs[-1]
    if last.get("accepted"):
        doc = copy.deepcopy(last)
        doc["windows"], doc["named_on"] = windows, {"fitted_to_day": ends[-1]}
        earlier = ("day " if len(ends) == 2 else "days ") + " and ".join(f"{e:g}"
                                                                         for e in ends[:-1])
        doc["verdict"] = (f"fitted to {earlier}, nothing was accepted and the held-back "
                          f"history was not fitted within noise; diagnosed again with the "
                          f"history fitted to day {ends[-1]:g} (held back after): "
                          + last["verdict"])
        return doc, True
    doc = copy.deepcopy(docs[0])
    doc["windows"], doc["named_on"] = windows, None
    for d, e in zip(docs[1:], ends[1:]):
        doc["verdict"] += f". Diagnosed again with the history fitted to day {e:g}: " + \
            d["verdict"]
    return doc, False


def _window(doc: dict) -> dict:
    return {"fitted_to_day": doc["history_end_days"],
            "accepted": [a["id"] for a in doc.get("accepted", [])],
            "first_cause": doc["causes"][0]["id"] if doc["causes"] else None,
            "heldout_within_noise": doc.get("heldout_within_noise"),
            "gain": doc["gain"], "verdict": doc["verdict"]}
