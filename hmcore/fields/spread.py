"""How much of its prior's spread an ensemble keeps, and whether it collapsed.

An ES-MDA update of many cells with few members shrinks the members' spread also where the
data say nothing: the spurious correlations of a small ensemble (Emerick & Reynolds 2013;
Evensen 2009, ch. 15), which localisation limits. The spread left is not wrong by itself
(data that inform a field should narrow it); against a known truth it is: a truth drawn like
a member lies, on average over the cells, about one spread from the members' mean (times
sqrt(1 + 1/N)). A posterior whose mean is :data:`COLLAPSED` times farther from the truth,
in its own spreads, than the prior's was is surer than it is right: the update collapsed it.
A prior already that far from the truth misses it, which no update repairs.

Pure numpy: ``(members, cells)`` in update space in, floats out; a member left out of an
update is a row of NaN and is not counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

COLLAPSED = 2.0
"""The factor on RMSE of the mean to the truth over the members' spread: above it for the
prior, the prior misses the truth; above it times the prior's (at least 1) for the posterior,
the update collapsed the ensemble (the members are, on average over the cells, less than half
as spread as their mean is far from the truth, and the update made it so)."""


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
    def prior_holds_truth(self) -> bool:
        """The prior's RMSE over spread at most :data:`COLLAPSED`: the truth is within the
        prior's reach (True when unknown, as nothing says otherwise)."""
        return not self.error_to_spread[0] > COLLAPSED

    @property
    def collapsed(self) -> bool:
        """The update made the ensemble surer than right: the posterior's RMSE over spread
        above :data:`COLLAPSED` times the prior's (or times 1, when the prior's is below 1).
        A prior that misses the truth already (PUNQ-S3's first prior: 2.6) is not called
        collapsed for keeping that distance (False when the truth is unknown)."""
        prior, posterior = self.error_to_spread
        base = max(1.0, prior) if math.isfinite(prior) else 1.0
        return bool(posterior > COLLAPSED * base)


def field_spread(field: str, prior: np.ndarray, posterior: np.ndarray,
                 truth: np.ndarray | None = None, space: str = "") -> FieldSpread:
    """:class:`FieldSpread` of ``prior`` and ``posterior`` ``(members, cells)`` against
    ``truth`` ``(cells,)`` when given."""
    if truth is None:
        return FieldSpread(field, spread(prior), spread(posterior), space=space)
    return FieldSpread(field, spread(prior), spread(posterior), mean_error(prior, truth),
                       mean_error(posterior, truth), space)
