"""Dating: did a well's productivity change during the history, and from which report date?

A completion change at day ``D`` (damage, scale, a stimulation) acts, to first order, like the
same change from the start with its sensitivity cut to the points after ``D``: the drawdown of a
rate-controlled well jumps when its productivity index does. So the well-skin probe of the
ranking (:mod:`hmcore.diagnosis.screening`) dates it without another run: for each report date
``D`` the score test of the cut sensitivity ``j * 1[t > D]`` against the calibrated residual
(the globals projected out, :func:`hmcore.diagnosis.attribution.score_test`) gives
``chi2(D)``; the best date's ``chi2`` less the undated one is the evidence for a date.

The decision comes from the noise model and the data counts, not a tuned number: with whitened
residuals (standard normal under the noise model) a date chosen among ``K`` scanned ones adds
one free parameter picked from ``K``; the gain is kept when it exceeds the chi-square(1)
quantile at ``alpha / K`` (a Bonferroni bound over the dates, the same as the screening's
:func:`hmcore.diagnosis.settings.noise_line`; ``K``
counts the dates scanned over every well, so that the family-wise false-alarm rate of a
diagnosis is ``alpha``). A kept
date becomes a candidate (:func:`hmcore.diagnosis.extensions.dated_productivity`) that gets its
own probe run and is ranked and recalibrated like any other. Nothing here simulates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from hmcore.diagnosis.attribution import score_test
from hmcore.diagnosis.settings import noise_line


@dataclass(frozen=True)
class Dating:
    """The date scan of one well."""

    well: str
    day: float
    """The best start day (a report day; the change acts on the points after it)."""
    chi2_dated: float
    chi2_undated: float
    threshold: float
    dates_scanned: int

    @property
    def gain(self) -> float:
        return self.chi2_dated - self.chi2_undated

    @property
    def dated(self) -> bool:
        """Does the evidence say the change has a start date (beyond the scan's noise)?"""
        return self.dates_scanned > 0 and self.gain > self.threshold

    def to_dict(self) -> dict:
        return {"well": self.well, "day": self.day, "chi2_dated": self.chi2_dated,
                "chi2_undated": self.chi2_undated, "gain": self.gain,
                "threshold": self.threshold, "dates_scanned": self.dates_scanned,
                "dated": self.dated}


def scan_days(report_days: tuple[float, ...] | list[float], days: np.ndarray,
              at_well: np.ndarray, min_after: int) -> list[float]:
    """Report days worth scanning: after the first fitted point, with at least ``min_after``
    of the well's fitted points (``at_well`` marks them in ``days``) after them."""
    if not at_well.any():
        return []
    well_days = np.sort(days[at_well])
    first = float(days.min())
    out = []
    for d in report_days:
        if d <= first + 1e-9:
            continue
        if np.count_nonzero(well_days > d + 1e-9) < min_after:
            break
        out.append(float(d))
    return out


def date_well(well: str, r0: np.ndarray, j: np.ndarray, days: np.ndarray, Q: np.ndarray,
              candidates: list[float], alpha: float, n_tests: int | None = None) -> Dating:
    """The date scan of ``well``: ``j`` its undated sensitivity (whitened, one entry per
    fitted point, ``days`` theirs), ``Q`` the globals' basis, ``candidates`` the days tried;
    ``n_tests``: the dates scanned over every well (the Bonferroni count; default this
    well's)."""
    undated = score_test(r0, j, Q).chi2
    best_day, best = float("nan"), -np.inf
    for d in candidates:
        c = score_test(r0, np.where(days > d + 1e-9, j, 0.0), Q).chi2
        if c > best:
            best_day, best = d, c
    if not candidates:
        best = undated
    return Dating(well, best_day, float(best), float(undated),
                  noise_line(n_tests or len(candidates), alpha), len(candidates))


def choose(datings: list[Dating], n_max: int) -> list[Dating]:
    """The dated wells worth a candidate: those whose date beats its threshold, the largest
    dated chi2 first, at most ``n_max``."""
    kept = [d for d in datings if d.dated]
    return sorted(kept, key=lambda d: -d.chi2_dated)[:max(n_max, 0)]
