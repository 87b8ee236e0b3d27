"""How much of its prior's spread an ensemble keeps, and whether it collapsed.

An ES-MDA update of many cells with few members shrinks the members' spread also where the
data say nothing: the spurious correlations of a small ensemble (Emerick & Reynolds 2013;
Evensen 2009, ch. 15), which localisation limits. The spread left is not wrong by itself
(data that inform a field should narrow it); against a known truth it is: a truth drawn like
a member lies, on average over the cells, about one spread from the members' mean (times
sqrt(1 + 1/N)), and an ensemble whose mean is :data:`COLLAPSED` spreads or more from the
truth is surer than it is right.

Pure numpy: ``(members, cells)`` in update space in, floats out; a member left out of an
update is a row of NaN and is not counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

COLLAPSED = 2.0
"""RMSE of the mean to the truth over the members' spread above which a posterior is called
collapsed: the members are, on average over the cells, half as spread as their mean is far
from the truth (a truth drawn from the prior gives 0.9-1.1 for the prior, measured on the
small field case's hidden truths)."""


def kept(members: np.ndarray) -> np.ndarray:
    """The rows of ``members`` ``(members, cells)`` with no NaN, as float64."""
    X = np.asarray(members, np.float64)
    return X[np.isfinite(X).all(axis=1)]


def spread(members: np.ndarray) -> float:
    """The members' spread: the root of the mean over cells of their variance (ddof 1); NaN
    with fewer than two members."""
    X = kept(members)
    if len(X) < 2:
        return float("nan")
    return float(np.sqrt(np.mean(X.var(axis=0, ddof=1))))


def mean_error(members: np.ndarray, truth: np.ndarray) -> float:
    """RMSE over cells of the members' mean to ``truth`` ``(cells,)``; NaN with no member."""
    X = kept(members)
    if not len(X):
        return float("nan")
    return float(np.sqrt(np.mean((X.mean(axis=0) - np.asarray(truth, np.float64)) ** 2)))


def error_to_spread(error: float, spread_: float) -> float:
    """``error / spread``; infinite for an error with no spread at all, NaN when unknown."""
    if spread_ > 0:
        return error / spread_
    return math.inf if spread_ == 0 and error > 0 else math.nan


@dataclass(frozen=True)
class FieldSpread:
    """One field's spread in the prior and the posterior and, when the truth is known, the
    RMSE of each mean to it (NaN when unknown)."""

    field: str
    sd_prior: float
    sd_posterior: float
    rmse_prior: float = math.nan
    rmse_posterior: float = math.nan
    space: str = ""
    """``log10`` for a field updated in log space, else ``value``; "" when not stated."""

    @property
    def kept(self) -> float:
        """The posterior's spread over the prior's."""
        return error_to_spread(self.sd_posterior, self.sd_prior)

    @property
    def error_to_spread(self) -> tuple[float, float]:
        """(prior, posterior) RMSE to the truth over spread (NaN when the truth is unknown)."""
        return (error_to_spread(self.rmse_prior, self.sd_prior),
                error_to_spread(self.rmse_posterior, self.sd_posterior))

    @property
    def collapsed(self) -> bool:
        """The posterior's RMSE over spread above :data:`COLLAPSED` (False when unknown)."""
        return bool(self.error_to_spread[1] > COLLAPSED)


def field_spread(field: str, prior: np.ndarray, posterior: np.ndarray,
                 truth: np.ndarray | None = None, space: str = "") -> FieldSpread:
    """:class:`FieldSpread` of ``prior`` and ``posterior`` ``(members, cells)`` against
    ``truth`` ``(cells,)`` when given."""
    if truth is None:
        return FieldSpread(field, spread(prior), spread(posterior), space=space)
    return FieldSpread(field, spread(prior), spread(posterior), mean_error(prior, truth),
                       mean_error(posterior, truth), space)
