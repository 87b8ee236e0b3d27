"""Which observed responses carry information about the model, and the macro scores over those
that do.

A well's series of one response (its oil rate, its water cut, ...) in one period (fitted or
held back) carries no information when

* it is the well's **rate control**: the simulator produces that rate by construction, so every
  model matches it (C_match 100). Known from the deck's history control (``WCONHIST`` /
  ``WCONINJH`` CMODE: the ``controlled`` rows of the case's history, left out of the fit, see
  :func:`hmcore.eclipse.history.controlled_mask`) or, for a history that gives its oil rate
  without sigma, the oil rate the noise reads as the rate control (``sigma_source`` ``rate``,
  :func:`hmcore.scoring.noise_fill.fill_sigma`);
* it is **within its noise of zero**: a zero series fits it within the noise (no value beyond
  :data:`hmcore.scoring.noise.Z_BEYOND_NOISE` sigma of zero, and the mean square of
  observed / sigma within that many standard deviations of its noise-only mean). A dry well's
  water cut is noise clipped at zero: any model with a rate about right scores C_match about
  50 % on it (NMSE about 1), the truth too;
* it is **within the noise floor of zero**: the noise estimate's own flag
  (:attr:`hmcore.scoring.observations.ObservationSet.uninformative`, on the fitted period).
"""

from __future__ import annotations

import math
from enum import Enum

import numpy as np
import pandas as pd

from hmcore.scoring.metrics import CATEGORIES, macro_scores
from hmcore.scoring.misfit import CATEGORY_OF, PRIMARY
from hmcore.scoring.noise import Z_BEYOND_NOISE

INFO_COLUMNS = ["period", "well", "category", "quantity", "informative", "why"]


class NoInformation(str, Enum):
    """Why a series carries no information (the words the report prints)."""

    RATE_CONTROL = "rate control"
    NEAR_ZERO = "within its noise of zero"
    NOISE_FLOOR = "within the noise floor of zero"


def within_noise_of_zero(observed: np.ndarray, sigma: np.ndarray) -> bool:
    """True when a zero series fits ``observed`` within its noise ``sigma`` (rows without a
    finite positive sigma left out): no |observed / sigma| beyond ``Z_BEYOND_NOISE``, and
    their mean square at most ``1 + Z_BEYOND_NOISE * sqrt(2 / n)`` (pure noise has mean 1,
    standard deviation sqrt(2 / n) for n independent rows)."""
    y, s = np.asarray(observed, float), np.asarray(sigma, float)
    ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
    z = y[ok] / s[ok]
    if not z.size:
        return False
    return bool(np.abs(z).max() <= Z_BEYOND_NOISE
                and np.mean(z * z) <= 1.0 + Z_BEYOND_NOISE * math.sqrt(2.0 / z.size))


def information_table(rows: pd.DataFrame, controlled: pd.DataFrame | None = None,
                      floor: set[tuple[str, str]] = frozenset(),
                      history_end: float | None = None) -> pd.DataFrame:
    """One row per period, well and response category of the scored history: ``informative``
    and, when not, ``why`` (a :class:`NoInformation` value; '' when informative).

    ``rows``: an ObservationSet's rows (well, quantity, days, observed, sigma, sigma_source,
    flowing, period; GOR and water cut read while the well flows); ``controlled``: the case's
    history rows a well's history control fixes (well, quantity, days; not in ``rows``),
    split at ``history_end``; ``floor``: the (quantity, well) pairs the noise estimate flags
    (:func:`hmcore.scoring.noise_table.flagged_series`)."""
    out = []
    scored = rows[rows.quantity.isin(list(CATEGORY_OF))]
    inflow = scored.flowing.astype(bool) | ~scored.quantity.isin(["WGOR", "WWCT"])
    for (period, well, q), g in scored[inflow].groupby(["period", "well", "quantity"]):
        why = _why_not(g, (q, well) in floor and period == "fit")
        out.append((period, well, CATEGORY_OF[q], q, why is None, why or ""))
    if controlled is not None and len(controlled):
        end = math.inf if history_end is None else history_end
        periods = np.where(controlled.days.to_numpy(float) <= end + 1e-9, "fit", "heldout")
        known = {(p, w, q) for p, w, _, q, _, _ in out}
        for (period, well, q), _ in controlled.assign(period=periods).groupby(
                ["period", "well", "quantity"]):
            if q in CATEGORY_OF and (period, well, q) not in known:
                out.append((period, well, CATEGORY_OF[q], q, False,
                            NoInformation.RATE_CONTROL.value))
    return pd.DataFrame(out, columns=INFO_COLUMNS)


def _why_not(series: pd.DataFrame, floor_flag: bool) -> str | None:
    """Why one well's series of one quantity in one period carries no information (None: it
    does)."""
    if (series.sigma_source == "rate").all():
        return NoInformation.RATE_CONTROL.value
    if within_noise_of_zero(series.observed.to_numpy(float), series.sigma.to_numpy(float)):
        return NoInformation.NEAR_ZERO.value
    if floor_flag:
        return NoInformation.NOISE_FLOOR.value
    return None


def uninformative(info: pd.DataFrame, period: str) -> dict[tuple[str, str], str]:
    """(well, category) -> why, for the series of ``period`` that carry no information."""
    sel = info[(info.period == period) & ~info.informative.astype(bool)]
    return {(r.well, r.category): r.why for r in sel.itertuples()}


def informative_macro(metrics: dict, info: pd.DataFrame, period: str) -> dict:
    """The paper's macro (:func:`hmcore.scoring.metrics.macro_scores`) over the primary
    categories of ``metrics`` that carry information in ``period``: a category is left out
    when every well's series of it carries none. ``{nmse, r2, cmatch, includes: [category],
    left_out: {category: why}}``."""
    cats = metrics.get("categories") or {}
    mine = info[info.period == period]
    includes, left_out = [], {}
    for cat in (c for c in CATEGORIES if c in PRIMARY):  # the paper's order
        rows = mine[mine.category == cat]
        if len(rows) and not rows.informative.astype(bool).any():
            left_out[cat] = ", ".join(sorted(set(rows.why)))
        elif cat in cats and cats[cat].get("n"):
            includes.append(cat)
    return {**macro_scores(cats, includes), "includes": includes, "left_out": left_out}


def information_grid(info: pd.DataFrame, period: str, wells: list[str]) -> pd.DataFrame:
    """Well x category table of ``period``: 'yes' where the series carries information, else
    why not ('' where the well has no such series)."""
    marks = uninformative(info, period)
    mine = info[info.period == period]
    cats = [c for c in CATEGORIES if c in set(mine.category)]
    grid = []
    for well in wells:
        have = set(mine.category[mine.well == well])
        grid.append({"well": well, **{c: marks.get((well, c), "yes" if c in have else "")
                                      for c in cats}})
    return pd.DataFrame(grid, columns=["well", *cats])
