"""How a series' noise scales with its level: absolute, relative to the value, or relative with
a minimum (ERT's ABS / REL / RELMIN), chosen by how the spread of the detrended series grows
with the signal's level; and the level of a series clipped at 0 (a dry water cut).

* :class:`NoiseScale` - the noise of row ``i`` is ``level * max(m_i, knee)`` (``m_i`` the
  signal's level at the row, :func:`smoothed_level`): ``knee`` infinite is an absolute noise,
  0 a noise relative to the value, in between relative with a minimum ``level * knee``. Its
  contrasts are taken on the value or on the logarithm (``space``: a signal growing by decades
  is closer to a line on the logarithm), with the rows weighted by the noise the scale gives
  them (:attr:`hmcore.scoring.noise.NoiseSeries.weight`).
* :func:`choose_scale` - the scales whose restricted likelihood, under a Laplace law of the
  contrasts (a contrast of 10,000 sigma counts as such, where the clipped mean square of the
  level estimate would cap it) with the Jacobian of the logarithm, is within
  :data:`SCALE_MARGIN` of the best are supported by the data; of those, the one never far
  below another on any row of the segment (the quantity's default when it is).
* :func:`censored_sigma` - the level of a series clipped at 0 (:data:`CENSORED_SHARE`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from statistics import NormalDist

import numpy as np

from hmcore.scoring.noise import MIN_CONTRASTS, NoiseFit, NoiseSeries, fit_noise

SCALE_MARGIN = 2.0
"""Scales whose log-likelihood is within this of the best one's (a factor e^2 in likelihood)
are supported by the data (:func:`choose_scale`)."""


KNEE_COST = 0.5
"""A relative noise with a minimum has one parameter more (the knee): it pays this times the
logarithm of the number of contrasts (the Bayesian information criterion)."""


SHORTFALL = 1.5
"""A scale the data support may fall short of another supported one by this factor on a row
(the accuracy the estimate aims at); beyond it the choice goes to one that does not."""


LEVEL_ROWS = 5
"""The signal's level at a row: the median of ``|value|`` over this many rows centred on it
(on a monotone signal the row's own value; the noise of one row does not set its weight)."""


KNEES = 7
"""Knees compared between the 5th and 95th percentiles of the level, geometrically spaced."""


LEVEL_SPAN = 3.0
"""Knees are compared only where the level spans more than this factor (5th to 95th
percentile): over a narrower span an absolute and a relative noise are the same."""


@dataclass(frozen=True)
class NoiseScale:
    """Row ``i``'s noise is ``level * max(m_i, knee)``; absolute when ``knee`` is infinite.
    ``space``: ``value`` or ``log``, the series whose contrasts estimate ``level``."""

    space: str
    knee: float

    @property
    def mode(self) -> str:
        """ERT's words: ``absolute`` (ABS), ``relative`` (REL), ``relative_min`` (RELMIN)."""
        if math.isinf(self.knee):
            return "absolute"
        return "relative" if self.knee <= 0 else "relative_min"

    def weight(self, level: np.ndarray) -> np.ndarray | None:
        """Each row's noise in the series' space relative to ``level`` (None: the same on
        every row): ``max(m, knee)`` on the value, ``max(m, knee) / m`` on the logarithm (an
        absolute noise there is ``1 / m``; a level of 0 counts as a billionth of the
        largest)."""
        if (self.space, self.mode) in (("value", "absolute"), ("log", "relative")):
            return None
        m = np.abs(np.asarray(level, float))
        top = float(np.nanmax(m)) if np.isfinite(m).any() else 1.0
        m = np.where(np.isfinite(m), np.maximum(m, 1e-9 * top), top)
        if self.space == "value":
            return np.maximum(m, self.knee)
        return 1.0 / m if self.mode == "absolute" else np.maximum(m, self.knee) / m

    def row_sigma(self, level: float, m: np.ndarray) -> np.ndarray:
        """The noise of rows whose signal's level is ``m``, in the value's units."""
        m = np.abs(np.asarray(m, float))
        if self.mode == "absolute":
            return np.full(m.size, float(level))
        return level * np.maximum(m, self.knee)

    def describe(self, level: float) -> dict:
        """The scale in the noise report's words."""
        out = {"noise_model": self.mode, "space": self.space}
        if self.mode == "relative_min":
            out |= {"knee": self.knee, "relative_min": level * self.knee}
        return out


ABSOLUTE_NOISE = NoiseScale("value", math.inf)
RELATIVE_NOISE = NoiseScale("log", 0.0)


def smoothed_level(values: np.ndarray, part: np.ndarray | None = None,
                   rows: int = LEVEL_ROWS) -> np.ndarray:
    """The signal's level along a series: the running median of ``|values|`` over ``rows``
    rows centred on each (fewer at the ends; NaN values ignored); with ``part`` (a boolean per
    row: the fitted period) the rows in and out of it each on their own."""
    v = np.abs(np.asarray(values, float))
    if part is not None:
        part = np.asarray(part, bool)
        out = np.empty(v.size)
        for rows_of in (part, ~part):
            out[rows_of] = smoothed_level(v[rows_of], rows=rows)
        return out
    half = rows // 2
    out = np.full(v.size, np.nan)
    for i in range(v.size):
        window = v[max(0, i - half):i + half + 1]
        window = window[np.isfinite(window)]
        if window.size:
            out[i] = float(np.median(window))
    return out


@dataclass(frozen=True)
class ScaleData:
    """One segment's fitted rows for :func:`choose_scale`: the series on the value (or the
    residual) and on the logarithm (NaN where the value is not positive), the signal's level
    per row and the observed values (the logarithm's Jacobian)."""

    plain: NoiseSeries
    log: NoiseSeries
    level: np.ndarray
    observed: np.ndarray

    def series(self, scale: NoiseScale, same_rows: bool = False) -> NoiseSeries:
        """The series ``scale`` estimates from, weighted; ``same_rows``: the value's series
        on the logarithm's rows only (so that every scale is judged on the same contrasts)."""
        base = self.log if scale.space == "log" else self.plain
        if same_rows and scale.space == "value":
            base = replace(base, values=np.where(np.isfinite(np.asarray(self.log.values, float)),
                                                 base.values, np.nan))
        return replace(base, weight=scale.weight(self.level))

    def jacobian(self) -> float:
        """``sum log |y|`` over the contrasts of the logarithm's chunks (a chunk of n rows gives
        n - 2): the density of the values from that of their logarithm."""
        y = np.abs(np.asarray(self.observed, float))
        return float(sum((c.size - 2) * np.mean(np.log(y[c])) for c in self.log.chunks()))


def candidates(data: list[ScaleData]) -> list[NoiseScale]:
    """Absolute and relative on either space (an absolute noise on a signal growing by decades
    is better told from the signal on the logarithm), and relative with a minimum at
    :data:`KNEES` knees on either space where the fitted level spans more than
    :data:`LEVEL_SPAN`."""
    out = [ABSOLUTE_NOISE, RELATIVE_NOISE, NoiseScale("value", 0.0), NoiseScale("log", math.inf)]
    m = np.concatenate([np.abs(np.asarray(d.level, float)) for d in data]) if data else \
        np.zeros(0)
    m = m[np.isfinite(m) & (m > 0)]
    if m.size < 2:
        return out
    lo, hi = np.percentile(m, [5, 95])
    if lo > 0 and hi > LEVEL_SPAN * lo:
        for knee in np.geomspace(lo, hi, KNEES):
            out += [NoiseScale("value", float(knee)), NoiseScale("log", float(knee))]
    return out


def laplace_cost(fit: NoiseFit, jacobian: list[float]) -> tuple[float, int]:
    """Negative log-likelihood of a weighted fit's contrasts under a Laplace law with each
    series' own scale (``n log mean|u| + log-determinant + Jacobian``, up to a constant), over
    the series with at least :data:`hmcore.scoring.noise.MIN_CONTRASTS` contrasts; and their
    number of contrasts."""
    total, n = 0.0, 0
    for u, term, jac in zip(fit.contrasts, fit.terms, jacobian):
        if u.size < MIN_CONTRASTS:
            continue
        b = float(np.mean(np.abs(u)))
        if not b > 0:
            continue
        total += u.size * math.log(b) + term + jac
        n += u.size
    return total, n


def unseen_levels(data: list[ScaleData]) -> list[np.ndarray]:
    """Per series, the levels of its fitted rows that no contrast sees: outside the range of
    the levels of the rows in any series' chunks, widened by :data:`SHORTFALL` (PUNQ-S3's
    water cut: its contrasts all in the first year, 1e-6 to 7e-6; a rise to 0.04 unseen)."""
    seen = [np.abs(np.asarray(d.level, float))[np.concatenate(c)]
            for d in data if (c := d.log.chunks())]
    seen = np.concatenate(seen) if seen else np.zeros(0)
    seen = seen[np.isfinite(seen) & (seen > 0)]
    out = []
    for d in data:
        m = np.abs(np.asarray(d.level, float))
        m = m[np.isfinite(m) & (m > 0)]
        if seen.size:
            m = m[(m < seen.min() / SHORTFALL) | (m > seen.max() * SHORTFALL)]
        out.append(m)
    return out


def row_sigmas(scale: NoiseScale, fit: NoiseFit, levels: list[np.ndarray]) -> np.ndarray:
    """The sigma ``scale`` gives rows of the signal's levels ``levels`` (per series, positive)
    from the levels of ``fit`` (a series without its own level takes the level pooled over
    all)."""
    pooled = fit.pooled(range(len(levels)))
    out = [np.zeros(0)]
    for level, m in zip(fit.sigma, levels):
        level = level if math.isfinite(level) and level > 0 else pooled
        if m.size and math.isfinite(level):
            out.append(scale.row_sigma(level, m))
    return np.concatenate(out)


def choose_scale(data: list[ScaleData], rho: float, default: NoiseScale
                 ) -> tuple[NoiseScale, dict]:
    """The scale of a quantity's noise (one for its segments, each with its own level) and the
    cost of each scale compared (``scores``: mode, space, knee -> cost less the default's).

    Every scale is judged on the same rows (those with a positive value) at correlation
    ``rho`` (:func:`laplace_cost`; a knee pays :data:`KNEE_COST` times the log of the number
    of contrasts). The scales within :data:`SCALE_MARGIN` of the best are those the data
    support. Where some rows are of a level no contrast sees (:func:`unseen_levels`: a water
    cut of 0.04 in PUNQ-S3's 3-row runs when every contrast is from the first year, at 1e-6
    to 7e-6), their sigmas may differ most there: an absolute level read from the first year
    puts the last rows thousands of sigma away if the noise is relative, and a relative one
    the first rows if it is absolute. Then the one chosen is never far below another
    supported one on any row: the default if none exceeds it on a row by more than
    :data:`SHORTFALL`, else the likeliest that none exceeds by more, else the one exceeded
    least. Where the contrasts see every level: the default if supported, else the
    likeliest."""
    if not data:
        return default, {}
    jac = [d.jacobian() for d in data]
    zero = [0.0] * len(data)
    costs: dict[NoiseScale, float] = {}
    fits: dict[NoiseScale, NoiseFit] = {}
    for scale in candidates(data):
        fit = fit_noise([d.series(scale, same_rows=True) for d in data], rho=rho)
        cost, n = laplace_cost(fit, jac if scale.space == "log" else zero)
        if n:
            knee = KNEE_COST * math.log(n) if scale.mode == "relative_min" else 0.0
            costs[scale], fits[scale] = cost + knee, fit
    if default not in costs:
        return default, {}
    best = min(costs.values())
    supported = [s for s, c in costs.items() if c <= best + SCALE_MARGIN]
    if any(m.size for m in unseen_levels(data)):
        levels = [np.abs(np.asarray(d.level, float)) for d in data]
        levels = [m[np.isfinite(m) & (m > 0)] for m in levels]
    else:
        levels = [np.zeros(0) for _ in data]
    sigmas = {s: row_sigmas(s, fits[s], levels) for s in supported}
    top = np.max(np.stack([sigmas[s] for s in supported]), axis=0)
    shortfall = {s: float(np.max(top / sigmas[s])) if sigmas[s].size else 1.0
                 for s in supported}
    fine = [s for s in supported if shortfall[s] <= SHORTFALL]
    if default in fine:
        chosen = default
    elif fine:
        chosen = min(fine, key=costs.__getitem__)
    else:
        chosen = min(supported, key=shortfall.__getitem__)
    base = costs[default]
    scores = {f"{s.mode} {s.space} {s.knee:.3g}": round(float(c - base), 2)
              for s, c in costs.items()}
    return chosen, scores


# ============================================================================ clipped at 0
CENSORED_SHARE = 0.15
"""A segment with at least this share of its values exactly at 0 is read as noise clipped
there (:func:`censored_sigma`)."""


def censored_sigma(values: np.ndarray, bound: float = 0.0) -> float:
    """Noise level of a series clipped at ``bound`` (the water cut of a dry well, its noise
    clipped at 0) about a level that does not move: the maximum-likelihood sigma of a normal
    law censored at ``bound`` (a Tobit model), profiled over ``mu / sigma`` on a grid. NaN
    when fewer than 3 values are above the bound."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)] - bound
    x = v[v > 1e-12]
    n0, n1 = int(v.size - x.size), int(x.size)
    if n1 < 3:
        return float("nan")
    nd = NormalDist()
    sx, sxx = float(x.sum()), float((x * x).sum())
    best = (-math.inf, float("nan"))
    for k in np.linspace(-3.0, 3.0, 241):
        s = (k * sx + math.sqrt(k * k * sx * sx + 4.0 * sxx * n1)) / (2.0 * sxx)  # 1 / sigma
        loglik = n1 * math.log(s) - 0.5 * (s * s * sxx - 2 * k * s * sx + k * k * n1)
        if n0:
            loglik += n0 * math.log(max(nd.cdf(-k), 1e-300))
        if loglik > best[0]:
            best = (loglik, 1.0 / s)
    return float(best[1])
