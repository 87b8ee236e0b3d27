"""Forecast with uncertainty from a campaign's runs: which runs, and their spread at the end.

Every simulator call runs the deck's whole schedule, so a forecast past the history needs no
new simulation: the members are runs the campaign already made. Members: the posterior
ensemble when the method made one (ES-MDA's ``posterior`` calls: the updated ensemble, not
the mean and the redraws it adds with the budget left, and only its valid members: a member
the physics checks penalise is not a plausible model), otherwise the best K valid
calls (distinct parameters). Reported per quantity at the schedule's end (field cumulative
oil, water and gas; per well cumulative oil): P90, P50, P10 in the industry's exceedance
convention (P90 the low case: 90 % of members at or above it), and the truth's value beside
them when the case's truth is known, with whether it falls inside [P90, P10].

The spread of near-best candidates is not a calibrated posterior: they are the K best points
one optimiser visited, not samples from the probability of the parameters given the data.
Only an ensemble method's posterior (ES-MDA, approximately: Gaussian and linear assumptions)
and the runs of draws from the Laplace posterior at the best call (:mod:`tasks.posterior`,
simulated after the fit: a campaign of at least 50 calls) are
read as one. :data:`MemberKind` says which; the report prints the matching sentence.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from hmcore.simulation.curves import FIELD, value_at_end

DEFAULT_MEMBERS = 10
TIE = 1e-5
"""Values within this share of each other are one value when a truth is judged against a
band (:func:`inside_band`)."""
FIELD_QUANTITIES = ("FOPT", "FWPT", "FGPT")
WELL_QUANTITIES = ("WOPT",)
LABELS = {"FOPT": "field cumulative oil", "FWPT": "field cumulative water",
          "FGPT": "field cumulative gas", "WOPT": "cumulative oil"}


class MemberKind(enum.Enum):
    NEAR_BEST = "near_best"      # the K best valid calls of an optimiser
    ENSEMBLE = "ensemble"        # an ensemble method's posterior members
    LAPLACE = "laplace"          # runs of parameter sets drawn from the Laplace posterior

    @property
    def caveat(self) -> str:
        if self is MemberKind.LAPLACE:
            return ("Members: runs of parameter sets drawn from the Laplace posterior at the "
                    "best call (the Gaussian of the linearised fit, within the parameter box "
                    "and the physics checks), simulated after the fit, apart from the budget. "
                    "It approximates the posterior of the case's parameters given the history "
                    "when the residuals are near linear in them; it knows nothing of what the "
                    "case leaves fixed, so read it as the band of these parameters' "
                    "uncertainty, not of the model's.")
        if self is MemberKind.ENSEMBLE:
            return ("Members: the ES-MDA posterior ensemble. It approximates the posterior "
                    "under ES-MDA's Gaussian, near-linear assumptions; read the band as an "
                    "approximate credible interval.")
        return ("Members: the best valid calls of the campaign. Their spread shows how much "
                "near-equally good matches disagree about the future; it is NOT a calibrated "
                "posterior (an optimiser's best points are not samples of the parameters "
                "given the data), so the band is no probability statement.")


@dataclass(frozen=True)
class Members:
    kind: MemberKind
    indices: tuple[int, ...]  # call indices (journal, from 0), best first for NEAR_BEST


def choose_members(records: list[dict], k: int = DEFAULT_MEMBERS,
                   objective: str = "E") -> Members:
    """The runs a forecast is made of (see the module docstring). ``records``: the campaign's
    consolidated rows (``index``, ``status``, ``E``, ``likelihood`` when it was scored,
    ``params``, ``phase``); the best K by ``objective``, the key that chose the campaign's best
    call (so that call is the first member)."""
    if k < 1:
        raise ValueError(f"a forecast needs at least 1 member, got k={k}")
    valid = [r for r in records if r.get("status") == "COMPLETE"
             and isinstance(r.get(objective), (int, float)) and math.isfinite(r[objective])]
    posterior = [r for r in valid if r.get("phase") == "posterior"]
    if len(posterior) >= 2:
        return Members(MemberKind.ENSEMBLE, tuple(sorted(r["index"] for r in posterior)))
    seen: set[tuple] = set()
    chosen = []
    for r in sorted(valid, key=lambda r: (r[objective], r["index"])):
        key = tuple(round(float(v), 6) for _, v in sorted(r["params"].items()))
        if key in seen:
            continue
        seen.add(key)
        chosen.append(r["index"])
        if len(chosen) == k:
            break
    return Members(MemberKind.NEAR_BEST, tuple(chosen))


def inside_band(p90: float, p10: float, truth: float) -> bool:
    """P90 <= truth <= P10 (P90 the low case), the ends widened by :data:`TIE` of the values:
    a well held at its rate control gives every member and the truth the same cumulative oil,
    up to the simulator's convergence (measured: 6e-6 of the value)."""
    tol = TIE * max(abs(p90), abs(p10), abs(truth))
    return bool(p90 - tol <= truth <= p10 + tol)


def forecast_table(curves: dict[int, pd.DataFrame], wells: list[str],
                   truth: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per quantity at the schedule's end: ``well`` (FIELD or a well), ``quantity``,
    ``label``, ``members``, ``P90``, ``P50``, ``P10``, ``min``, ``max``, ``end_days``, and
    ``truth`` / ``truth_inside`` (None when the truth is unknown). ``curves``: member call
    index -> that run's curves (:func:`hmcore.simulation.curves.read_curves`)."""
    targets = [(FIELD, q) for q in FIELD_QUANTITIES] + [(w, q) for w in wells
                                                        for q in WELL_QUANTITIES]
    rows = []
    for well, q in targets:
        values = np.array([value_at_end(c, well, q) for c in curves.values()], float)
        values = values[np.isfinite(values)]
        if values.size == 0:
            continue
        ends = [float(c.days.max()) for c in curves.values() if len(c)]
        t = value_at_end(truth, well, q) if truth is not None else float("nan")
        p90, p50, p10 = (float(np.quantile(values, p)) for p in (0.1, 0.5, 0.9))
        rows.append({"well": well, "quantity": q,
                     "label": LABELS[q] if well == FIELD else f"{well} {LABELS[q]}",
                     "members": int(values.size), "P90": p90, "P50": p50, "P10": p10,
                     "min": float(values.min()), "max": float(values.max()),
                     "end_days": max(ends) if ends else float("nan"),
                     "truth": t if math.isfinite(t) else None,
                     "truth_inside": inside_band(p90, p10, t) if math.isfinite(t) else None})
    return pd.DataFrame(rows, columns=["well", "quantity", "label", "members", "P90", "P50",
                                       "P10", "min", "max", "end_days", "truth",
                                       "truth_inside"])
