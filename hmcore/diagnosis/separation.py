"""What would tell explanations apart: from the runs already made (each explanation's fitted
model simulated over the whole schedule), the well, response and time at which two of them
predict most differently, in units of the noise sigma.

:func:`separations` is a pure numpy function of predictions on one time grid;
:func:`tabulate` puts the runs' response tables on that grid. Nothing here simulates.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

LINE = 2.0
"""Separation (in sigma) from which a single measurement tells two explanations apart at
about 84 % (a 2-sigma difference of means seen through one sigma of noise); the day the
difference first reaches it is the "after day" of the sentence."""

MEASURED = ("WBHP", "WOPR", "WWPR", "WGPR", "WGOR", "WWCT")
WORDS = {"WBHP": "BHP", "WOPR": "oil-rate", "WWPR": "water-rate", "WGPR": "gas-rate",
         "WGOR": "GOR", "WWCT": "water-cut"}


@dataclass(frozen=True)
class Separation:
    """Where explanations ``a`` and ``b`` predict most differently."""

    a: str
    b: str
    well: str
    quantity: str
    day: float
    """Where the difference is largest."""
    z: float
    """That difference over the noise sigma of the series (>= 0)."""
    from_day: float | None
    """The first day the difference reaches :data:`LINE` sigma (None: never)."""

    def sentence(self, history_end: float | None = None) -> str:
        """E.g. "a water-cut measurement at PRO-11 after day 3500 separates A from B by 4
        sigma (largest at day 4100)"; when they never differ by :data:`LINE` sigma, that no
        single measurement separates them, and where one comes closest."""
        what = WORDS.get(self.quantity, self.quantity)
        article = "an" if what[0] in "aeiou" else "a"
        if self.from_day is None:  # never LINE sigma apart: say so, and where they come closest
            return (f"no single measurement separates {self.a} from {self.b} by {LINE:g} "
                    f"sigma in the schedule run; the most, {self.z:.1f} sigma: {article} {what} "
                    f"measurement at {self.well} at day {self.day:.0f}")
        text = (f"{article} {what} measurement at {self.well} after day {self.from_day:.0f} "
                f"separates {self.a} from {self.b} by {self.z:.1f} sigma (largest at day "
                f"{self.day:.0f})")
        if history_end is not None and self.from_day is not None and \
                self.from_day <= history_end:
            text += (f" - from inside the fitted history already (to day {history_end:.0f}):"
                     " more measurements of it, or less noisy ones, would tell them apart")
        return text


def separations(ids: list[str] | tuple[str, ...], series: list[tuple[str, str]],
                days: np.ndarray, predictions: np.ndarray, sigma: np.ndarray,
                line: float = LINE) -> tuple[Separation, ...]:
    """For each pair of ``ids``, where their predictions differ most in sigma; the pairs in
    the order of ``ids`` (first with second, first with third, ..., second with third).

    ``series``: S (well, quantity) pairs; ``days``: shape (T,), increasing;
    ``predictions``: shape (M, S, T), M = len(ids), NaN where a model has no value;
    ``sigma``: shape (S,) or (S, T), the noise sigma (a series with no finite positive sigma
    is left out). A pair that never differs (all NaN) is left out."""
    p = np.asarray(predictions, float)
    sig = np.asarray(sigma, float)
    if sig.ndim == 1:
        sig = np.broadcast_to(sig[:, None], p.shape[1:])
    sig = np.where(np.isfinite(sig) & (sig > 0), sig, np.nan)
    days = np.asarray(days, float)
    out = []
    for i, j in itertools.combinations(range(len(ids)), 2):
        z = np.abs(p[i] - p[j]) / sig  # (S, T)
        if not np.any(np.isfinite(z)):
            continue
        s, t = np.unravel_index(np.nanargmax(np.where(np.isfinite(z), z, -1.0)), z.shape)
        above = np.flatnonzero(np.nan_to_num(z[s], nan=0.0) >= line)
        out.append(Separation(ids[i], ids[j], series[s][0], series[s][1], float(days[t]),
                              float(z[s, t]), float(days[above[0]]) if len(above) else None))
    return tuple(out)


def tabulate(responses: dict[str, pd.DataFrame], sigma: dict[tuple[str, str], float],
             quantities: tuple[str, ...] = MEASURED
             ) -> tuple[list[str], list[tuple[str, str]], np.ndarray, np.ndarray, np.ndarray]:
    """The runs' response tables (well, days, quantity, value; one per explanation id) on
    the first one's days: (ids, series, days (T,), predictions (M, S, T), sigma (S,)).
    ``sigma``: per (well, quantity), the noise sigma; series without one are left out;
    values are interpolated in time where a run's days differ."""
    ids = list(responses)
    if not ids:
        return [], [], np.zeros(0), np.zeros((0, 0, 0)), np.zeros(0)
    first = responses[ids[0]]
    days = np.unique(first["days"].to_numpy(float))
    series = sorted({(w, q) for w, q in zip(first["well"], first["quantity"])
                     if q in quantities and math.isfinite(sigma.get((w, q), math.nan))
                     and sigma[(w, q)] > 0})
    preds = np.full((len(ids), len(series), len(days)), np.nan)
    for m, k in enumerate(ids):
        df = responses[k]
        if df is None or df.empty:
            continue
        groups = {key: g for key, g in df.groupby(["well", "quantity"], sort=False)}
        for s, key in enumerate(series):
            g = groups.get(key)
            if g is None:
                continue
            g = g.sort_values("days")
            t, v = g["days"].to_numpy(float), g["value"].to_numpy(float)
            inside = (days >= t[0]) & (days <= t[-1])
            preds[m, s, inside] = np.interp(days[inside], t, v)
    return ids, series, days, preds, np.array([sigma[k] for k in series], float)
