"""Measurement noise: how it is described and how it is estimated from the data.

* :class:`NoiseModel` - the noise of a well's observed history as PUNQ-S3's description states
  it (BHP, GOR and water cut, before and after breakthrough, AR(1) in time). hmflow's
  generators draw their noise from it (:mod:`hmcore.scenarios.synthetic`,
  :mod:`hmcore.scenarios.hidden`); the estimator uses it as its default where a record allows
  no estimate.
* :func:`fit_noise` - noise levels and one AR(1) correlation from series without stated sigma,
  by restricted likelihood of contrasts free of a local line within each run of continuous
  signal (:class:`NoiseSeries`), whose rows may carry a relative noise weight (a noise that
  grows with the level: :mod:`hmcore.scoring.noise_scale` chooses it and has the level of a
  series clipped at 0); :func:`variogram_rho` the correlation of series whose sigma the data
  give. Used by :mod:`hmcore.scoring.noise_fill` for
  :class:`hmcore.scoring.observations.ObservationSet`.
* The floors and thresholds the estimate keeps to (:data:`SIGMA_FLOOR`,
  :data:`FLOOR_SIGNAL_SHARE`, ...).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

# --- observation noise (PUNQ-S3 style) --------------------------------------------------------
NOISE_RHO = 0.7
"""AR(1) correlation between consecutive observations of one well and quantity."""


BHP_SIGMA_FLOWING_BAR = 3.0


BHP_SIGMA_SHUTIN_BAR = 1.0


GOR_SIGMA_FRAC_BEFORE = 0.10


GOR_SIGMA_FRAC_AFTER = 0.25


GAS_BREAKTHROUGH_GOR_RATIO = 1.10
"""Gas breakthrough: GOR first exceeds the well's first flowing GOR by this factor."""


WCT_SIGMA_BEFORE = 0.02


WCT_SIGMA_AFTER = 0.05


WATER_BREAKTHROUGH_WCT = 0.01
"""Water breakthrough: water cut first exceeds this fraction. The one water-breakthrough
threshold of hmflow: the diagnosis, which sees it through noisy data, looks for the observed
water cut to pass it by two standard deviations of the noise before breakthrough
(:data:`hmcore.scoring.noise.WATER_BREAKTHROUGH_SEEN`)."""


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise of a well's observed history (PUNQ-S3's description, the model
    description's sigma table): Gaussian, correlated in time as a unit AR(1) series along each
    well's rows of one quantity. The one noise model of hmflow: the synthetic case
    (:func:`make_observed`) and the hidden-effect cases (:mod:`hmcore.scenarios.hidden`) both
    draw their noise from it (:func:`noisy_series`)."""

    rho: float = NOISE_RHO
    """AR(1) correlation between consecutive observations of one well and quantity."""
    bhp_flowing: float = BHP_SIGMA_FLOWING_BAR
    """BHP sigma (bar) while the well flows ..."""
    bhp_shut_in: float = BHP_SIGMA_SHUTIN_BAR
    """... and while it is shut in."""
    gor_before: float = GOR_SIGMA_FRAC_BEFORE
    """GOR sigma as a fraction of the true GOR before gas breakthrough ..."""
    gor_after: float = GOR_SIGMA_FRAC_AFTER
    """... and after it."""
    gas_breakthrough_ratio: float = GAS_BREAKTHROUGH_GOR_RATIO
    """Gas breakthrough: GOR first exceeds the well's first flowing GOR by this factor."""
    wct_before: float = WCT_SIGMA_BEFORE
    """Water-cut sigma before water breakthrough ..."""
    wct_after: float = WCT_SIGMA_AFTER
    """... and after it."""
    water_breakthrough_wct: float = WATER_BREAKTHROUGH_WCT
    """Water breakthrough: water cut first exceeds this fraction."""

    def describe(self) -> dict:
        """The noise model in words and numbers (``truth.json``'s ``noise``)."""
        return {
            "model": "sigma * AR(1) unit-variance series along each well's rows of a quantity",
            "ar1_rho": self.rho,
            "WOPR": "rate control, no noise (sigma left empty)",
            "WBHP_sigma_bar": {"flowing": self.bhp_flowing, "shut_in": self.bhp_shut_in},
            "WGOR_sigma_fraction_of_value": {"before_gas_breakthrough": self.gor_before,
                                             "after_gas_breakthrough": self.gor_after},
            "gas_breakthrough": f"GOR > {self.gas_breakthrough_ratio} x first flowing GOR",
            "WWCT_sigma": {"before_water_breakthrough": self.wct_before,
                           "after_water_breakthrough": self.wct_after},
            "water_breakthrough": f"WWCT > {self.water_breakthrough_wct}",
            "clipping": "WWCT to [0, 1], WGOR to >= 0",
        }


PUNQ_NOISE = NoiseModel()
"""PUNQ-S3's noise, the synthetic case's and the hidden-effect cases'."""


RESPONSE_OF = {"WBHP": "bhp", "WOPR": "oil", "WWPR": "water", "WGPR": "gas", "WGOR": "gor",
               "WWCT": "wct"}


SIGMA_FLOOR = {"WBHP": 0.3, "WWCT": 0.01, "WGOR_REL": 0.01, "RATE_REL": 0.01}
"""Smallest noise level an estimate may give: bar, fraction, relative GOR, relative rate (a
gauge's resolution: data rounded to a few digits would otherwise give a level near 0)."""


FLOOR_SIGNAL_SHARE = 0.01
"""A floor never sits above the signal it would hide: an absolute floor is at most this share
of a segment's typical value (a water cut of 3e-5 gets 3e-7, not 0.01). A series whose every
fitted value is within its quantity's floor of zero is also marked uninformative."""


RATE_STEP = 0.10
"""An observed oil rate that changes by more than this share between two rows starts a new run
of continuous signal (the BHP, GOR and water cut may step there)."""


AFTER_BREAKTHROUGH_DEFAULT = {"WWCT": PUNQ_NOISE.wct_after, "WGOR": PUNQ_NOISE.gor_after}
"""Noise after water / gas breakthrough when no well's record allows an estimate: typical
test-separator uncertainty, PUNQ-S3's description (WCT 0.05, GOR 25 %; see
:class:`hmcore.scoring.noise.NoiseModel`)."""


OIL_RATE_SIGMA_REL = 0.05
"""Noise of a measured oil rate without sigma (usually the rate control): 5 % of the value."""


OIL_RATE_SIGMA_MIN = 1.0


BREAKTHROUGH_SIGMAS = 2.0


WATER_BREAKTHROUGH_SEEN = WATER_BREAKTHROUGH_WCT + BREAKTHROUGH_SIGMAS * PUNQ_NOISE.wct_before
"""Water breakthrough as the diagnosis sees it in a noisy record: the water cut reaches
:data:`hmcore.scoring.noise.WATER_BREAKTHROUGH_WCT` (0.01, the one threshold) by
``BREAKTHROUGH_SIGMAS`` standard deviations of the noise before breakthrough (0.02): 0.05.
A measured water cut of 0.01 is within the noise of a dry well (1 sigma of 0.02 is 0.02)."""


GAS_BREAKTHROUGH_RATIO = 1.2
"""Gas breakthrough as the diagnosis sees it: the GOR 20 % above the well's initial one. The
synthetic history's threshold is 1.10 (:data:`hmcore.scoring.noise.GAS_BREAKTHROUGH_GOR_RATIO`);
1.2 is about that plus one standard deviation of the GOR noise before breakthrough (10 %),
where water takes two. Not derived from it like the water threshold: deriving it (1.32)
would move the noise segments of every diagnosis, left for after the generator sweep."""


Z_BEYOND_NOISE = 3.0


MAX_RHO = 0.9


# ============================================================================ noise estimation
RHO_GRID = tuple(round(0.05 * k, 2) for k in range(round(MAX_RHO / 0.05) + 1))
"""AR(1) correlations the profile likelihood of :func:`fit_noise` compares."""


CHUNK_ROWS = 6
"""Longest stretch of a run the local linear trend of :func:`fit_noise` spans (rows): long
enough to separate a trend from noise, short enough that a curved transient (a build-up, a
decline after reopening) is close to a line over it."""


MIN_CHUNK_ROWS = 3
"""A line through fewer rows leaves no contrast free of the trend."""


MIN_CONTRASTS = 3
"""Fewest trend-free contrasts from which one series' noise level is estimated; with fewer,
the series takes the level pooled over its group (the same segment in the other wells)."""


RHO_SUPPORT = 1.92
"""Correlations whose restricted log-likelihood is within this of the best one are supported by
the data (1.92: a 95 % likelihood-ratio interval)."""


RHO_WIDE = 0.5
"""A supported range of correlations wider than this means the data do not tell the correlation
(short runs between shut-ins): the noise report says so, and the levels assume the mean."""


UNCERTAIN_FACTOR = 1.5
"""A level whose range (sampling and the correlations the data support) reaches beyond this
factor of it is reported uncertain."""


SHRINK_CONTRASTS = 8
"""A well's own level counts as many contrasts as it has, the level of its kind pooled over all
wells as this many: a well with a few contrasts (a level from 4 is uncertain by a factor of
about 1.5) leans on the others, one with many keeps its own."""


CLIP = 3.5
"""Contrasts beyond this many robust standard deviations are clipped (a step the runs did not
catch, a breakthrough, a heavy-tailed gauge); the mean square is corrected for the clipping."""


def _winsorized_var(d: np.ndarray, clip: float = 4.0) -> float:
    """Variance of ``d`` about its median with values beyond ``clip`` robust SDs clipped."""
    if d.size < 2:
        return float("nan")
    m = float(np.median(d))
    s = 1.4826 * float(np.median(np.abs(d - m)))
    if s <= 0:
        return 0.0
    return float(np.mean(np.clip(d - m, -clip * s, clip * s) ** 2))


def robust_variogram(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Robust semivariogram ``gamma(h) = var(x_{t+h} - x_t) / 2``, h = 1..max_lag.

    The differences are centred on their median, so a linear trend does not count as noise,
    and clipped at 4 robust standard deviations, so jumps (rate changes, breakthroughs) do not
    either. NaN where the series is too short.
    """
    x = np.asarray(x, float)
    out = np.full(max_lag, np.nan)
    for h in range(1, max_lag + 1):
        if x.size - h >= 3:
            out[h - 1] = _winsorized_var(x[h:] - x[:-h]) / 2.0
    return out


@dataclass(frozen=True)
class NoiseSeries:
    """One well's rows of one noise segment, in the space the noise is additive in (the value,
    or its logarithm for a noise relative to the value).

    ``days`` is the time the signal's trend is linear in (default: the row number);
    ``position`` the row number along the well's whole series of the quantity, the lag unit
    of the AR(1) noise (default 0, 1, ...); ``run`` labels stretches of rows over which the
    signal is continuous: a shut-in, a rate change or a breakthrough between two rows starts
    a new run (default: one run); ``weight`` the noise of each row relative to the others
    (default: the same on every row): the noise of row i is ``sigma * weight[i]``, so a noise
    that grows with the signal's level is a weight (see :mod:`hmcore.scoring.noise_scale`)."""

    values: np.ndarray
    days: np.ndarray | None = None
    position: np.ndarray | None = None
    run: np.ndarray | None = None
    weight: np.ndarray | None = None
    chunk_rows: int | None = CHUNK_ROWS
    """The longest stretch one line spans (None: a whole run)."""

    def chunks(self) -> list[np.ndarray]:
        """Row indices of the stretches a local line is fitted to: each run without its first
        row (right after a change, the steepest part of a transient: a reopening's drawdown,
        a build-up's first day), cut into pieces of at most ``chunk_rows`` rows (none
        shorter than :data:`MIN_CHUNK_ROWS`)."""
        n = len(self.values)
        run = np.zeros(n, int) if self.run is None else np.asarray(self.run)
        out = []
        starts = np.flatnonzero(np.r_[True, run[1:] != run[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], n]):
            idx = np.arange(a + 1, b)
            idx = idx[np.isfinite(np.asarray(self.values, float)[idx])]
            if idx.size >= MIN_CHUNK_ROWS:
                out += np.array_split(idx, math.ceil(idx.size / (self.chunk_rows or idx.size)))
        return out


def _contrasts(y: np.ndarray, t: np.ndarray, p: np.ndarray, rho: float,
               w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Trend-free, uncorrelated contrasts of a stack of chunks of one length and their REML
    log-determinant terms.

    Each row of ``y`` (chunks x rows) is ``a + b t + sigma e`` with ``e`` AR(1) (correlation
    ``rho ** |p_i - p_j|``): the whitened values ``L^-1 y`` (``C = L L'``) projected off the
    whitened trend basis are ``rows - 2`` independent N(0, sigma^2) contrasts per chunk. The
    term ``log|L| + log|R|`` (R from the QR of the whitened basis) is the part of the
    restricted likelihood that depends on ``rho`` besides the contrasts. With row weights
    ``w`` (chunks x rows) the noise is ``sigma w_i e_i``: ``C_ij = w_i w_j rho^|p_i - p_j|``
    (generalized least squares; ``log|L|`` then holds ``sum log w``)."""
    k, n = y.shape
    lag = np.abs(p[:, :, None] - p[:, None, :])
    cov = rho ** lag if rho > 0 else np.broadcast_to(np.eye(n), (k, n, n))
    if w is not None:  # a row of weight 0 (a level of 0) takes its chunk's least positive one
        least = np.where(w > 0, w, np.inf).min(axis=1, keepdims=True)
        w = np.where(w > 0, w, np.where(np.isfinite(least), least, 1.0))
        cov = cov * w[:, :, None] * w[:, None, :]
    chol = np.linalg.cholesky(cov)
    tc = t - t.mean(axis=1, keepdims=True)
    basis = np.stack([np.ones((k, n)), tc / np.ptp(t, axis=1, keepdims=True)], axis=2)
    white = np.linalg.solve(chol, np.concatenate([basis, y[:, :, None]], axis=2))
    q, r = np.linalg.qr(white[:, :, :2], mode="complete")
    u = np.einsum("kij,ki->kj", q[:, :, 2:], white[:, :, 2])
    diag_l = np.log(np.diagonal(chol, axis1=1, axis2=2)).sum(axis=1)
    diag_r = np.log(np.abs(np.diagonal(r, axis1=1, axis2=2)[:, :2])).sum(axis=1)
    return u, diag_l + diag_r


def level_interval(n: int, z: float = 1.96) -> tuple[float, float]:
    """Factors on a noise level estimated from ``n`` independent contrasts giving its
    two-sided interval (95 % for z = 1.96): ``sqrt(n / chi2_n quantile)``, with the
    Wilson-Hilferty approximation of the chi-square quantiles."""
    if n <= 0:
        return 0.0, math.inf
    a = 2.0 / (9.0 * n)

    def chi2(zz: float) -> float:
        return n * max(1.0 - a + zz * math.sqrt(a), 1e-6) ** 3

    return math.sqrt(n / chi2(z)), math.sqrt(n / chi2(-z))


def _clip_factor(c: float) -> float:
    """E[min(z^2, c^2)] for a standard normal z: the mean square a clip at c keeps."""
    nd = NormalDist()
    return (2 * nd.cdf(c) - 1) - 2 * c * nd.pdf(c) + 2 * c * c * (1 - nd.cdf(c))


def robust_mean_square(u: np.ndarray, clip: float = CLIP) -> float:
    """Mean square of zero-mean contrasts with values beyond ``clip`` robust standard
    deviations clipped, corrected to be unbiased for Gaussian contrasts (NaN when empty)."""
    u = np.asarray(u, float)
    if u.size == 0:
        return float("nan")
    if u.size < 5:
        return float(np.mean(u * u))
    s = 1.4826 * float(np.median(np.abs(u)))
    if s <= 0:
        return float(np.mean(u * u))
    return float(np.mean(np.minimum(u * u, (clip * s) ** 2))) / _clip_factor(clip)


@dataclass(frozen=True)
class NoiseFit:
    """The noise of a set of series: a level per series (NaN: too few contrasts), the shared
    AR(1) correlation and each series' contrasts at that correlation (for pooling)."""

    sigma: tuple[float, ...]
    rho: float
    contrasts: tuple[np.ndarray, ...]
    rho_range: tuple[float, float] | None = None
    """The correlations the data support (restricted likelihood within
    :data:`RHO_SUPPORT` of its best); None when rho was given."""
    terms: tuple[float, ...] = ()
    """Each series' log-determinant term of the restricted likelihood at ``rho`` (with rho
    given): what a model of the noise's scale pays besides its contrasts."""

    @property
    def rho_identified(self) -> bool:
        """Whether the data tell the correlation (its supported range is narrow): otherwise
        the levels depend on the correlation assumed."""
        return self.rho_range is None or self.rho_range[1] - self.rho_range[0] <= RHO_WIDE

    def pooled(self, members) -> float:
        """One level from the contrasts of the series ``members`` together (NaN: none)."""
        u = [self.contrasts[i] for i in members]
        u = np.concatenate(u) if u else np.zeros(0)
        return math.sqrt(robust_mean_square(u)) if u.size >= MIN_CONTRASTS else float("nan")


class _Chunks:
    """Every chunk of a set of series, stacked by length for batched linear algebra."""

    def __init__(self, series: list[NoiseSeries]):
        self.n_series = len(series)
        by_len: dict[int, list[tuple]] = {}
        for i, s in enumerate(series):
            y = np.asarray(s.values, float)
            t = np.arange(y.size, dtype=float) if s.days is None else np.asarray(s.days, float)
            p = np.arange(y.size, dtype=float) if s.position is None else \
                np.asarray(s.position, float)
            w = np.ones(y.size) if s.weight is None else np.asarray(s.weight, float)
            for c in s.chunks():
                if np.ptp(t[c]) > 0:
                    by_len.setdefault(c.size, []).append((i, y[c], t[c], p[c], w[c]))
        self.weighted = any(s.weight is not None for s in series)
        self.stacks = [tuple(np.array([a[j] for a in v]) for j in range(5))
                       for v in by_len.values()]
        self.terms = np.zeros(self.n_series)

    def at(self, rho: float) -> tuple[list[np.ndarray], float]:
        """Each series' contrasts at ``rho`` and the sum of the log-determinant terms (each
        series' own in :attr:`terms`)."""
        parts: list[list[np.ndarray]] = [[] for _ in range(self.n_series)]
        self.terms = np.zeros(self.n_series)
        for owner, y, t, p, w in self.stacks:
            u, term = _contrasts(y, t, p, rho, w if self.weighted else None)
            np.add.at(self.terms, owner, term)
            for i, row in zip(owner, u):
                parts[i].append(row)
        return [np.concatenate(x) if x else np.zeros(0) for x in parts], float(self.terms.sum())


def fit_noise(series: list[NoiseSeries], rho: float | None = None,
              groups: list | None = None) -> NoiseFit:
    """Noise level of each series and one shared AR(1) correlation, by restricted likelihood.

    Model: within each chunk of a run (see :meth:`NoiseSeries.chunks`) the value is a line in
    ``days`` plus ``sigma_s`` times AR(1) noise of correlation ``rho`` along the rows. The
    lines are nuisance: only contrasts free of them are used (REML), so a trend, a rate step
    or a shut-in between runs never counts as noise. ``rho`` (unless given) is the mean of
    :data:`RHO_GRID` weighted by the restricted likelihood (a posterior mean under a flat
    prior: short runs often tell a correlation from a trend only weakly, and the mean does
    not jump to an end of the range on a flat likelihood), with one level per group of series
    (``groups``: a label per series, default one group per series) and, inside a group,
    each series' contrasts scaled by its own level at ``rho = 0``; a group pools the few
    contrasts of short series, which alone would let the level absorb the correlation. Each
    level is the robust mean square of its contrasts (:func:`robust_mean_square`) at the
    chosen ``rho``; a series with fewer than :data:`MIN_CONTRASTS` contrasts gets NaN (see
    :meth:`NoiseFit.pooled`).
    """
    chunks = _Chunks(series)
    labels = list(range(len(series))) if groups is None else list(groups)
    if rho is not None:
        per, _ = chunks.at(float(rho))
        return NoiseFit(_levels(per), float(rho), tuple(per), terms=tuple(chunks.terms))
    scale = None
    objective, fits = [], []
    for r in RHO_GRID:
        per, term = chunks.at(r)
        if scale is None:
            scale = _scales(per, labels)
        total = term
        pooled: dict = {}
        for u, g, sc in zip(per, labels, scale):
            if u.size and sc > 0:
                pooled.setdefault(g, []).append(u / sc)
        for g, parts in pooled.items():
            u = np.concatenate(parts)
            v = robust_mean_square(u) if u.size >= MIN_CONTRASTS else float("nan")
            if v > 0:
                total += 0.5 * u.size * math.log(v)
        objective.append(total)
        fits.append(per)
    obj = np.array(objective) - min(objective)
    weight = np.exp(-obj)
    mean = float(np.sum(weight * np.array(RHO_GRID)) / np.sum(weight))
    k = int(np.argmin(np.abs(np.array(RHO_GRID) - mean)))
    inside = [r for r, o in zip(RHO_GRID, obj) if o <= RHO_SUPPORT]
    return NoiseFit(_levels(fits[k]), RHO_GRID[k], tuple(fits[k]), (min(inside), max(inside)))


def _levels(per: list[np.ndarray]) -> tuple[float, ...]:
    return tuple(math.sqrt(robust_mean_square(u)) if u.size >= MIN_CONTRASTS else float("nan")
                 for u in per)


def _scales(per: list[np.ndarray], labels: list) -> list[float]:
    """Each series' own level at rho = 0 (its group's, when it has too few contrasts)."""
    group: dict = {}
    for u, g in zip(per, labels):
        group.setdefault(g, []).append(u)
    pooled = {g: math.sqrt(robust_mean_square(np.concatenate(v))) if sum(x.size for x in v)
              else 0.0 for g, v in group.items()}
    return [math.sqrt(robust_mean_square(u)) if u.size >= MIN_CONTRASTS else pooled[g]
            for u, g in zip(per, labels)]


def variogram_rho(series: list[np.ndarray]) -> float:
    """Lag-1 correlation shared by series of standardized values (the data's own sigma known),
    from robust variograms: the noise part of the variogram is ``(1 - rho^h)``, so
    ``gamma(2) / gamma(1) = 1 + rho``, pooled over the series (each weighted by its length, on
    its own scale); series shorter than 5 do not count. Only lags 1 and 2 are used: a smooth
    misfit left in a series adds ``c h^2`` and biases the estimate less the shorter the lags."""
    num = den = 0.0
    for s in series:
        g = robust_variogram(s, 2) if len(s) >= 5 else np.full(2, np.nan)
        if np.isfinite(g).all() and g.sum() > 0:
            num += len(s) * g[1] / g.sum()
            den += len(s) * g[0] / g.sum()
    rho = num / den - 1.0 if den > 0 else 0.0
    return float(min(max(rho, 0.0), MAX_RHO))


def estimate_noise(series: list[np.ndarray], rho: float | None = None
                   ) -> tuple[list[float], float]:
    """Noise level of each series (one run each, rows equally spaced) and one shared AR(1)
    correlation: :func:`fit_noise` on plain arrays. NaN for a series too short to estimate."""
    fit = fit_noise([NoiseSeries(np.asarray(s, float)) for s in series], rho)
    return list(fit.sigma), fit.rho


def breakthrough_index(values: np.ndarray, threshold: float, persist: int = 2) -> int | None:
    """First index from which ``persist`` consecutive values reach ``threshold`` (None if never)."""
    ok = np.asarray(values, float) >= threshold
    for i in range(len(ok)):
        if ok[i:i + persist].all() and (i + persist <= len(ok) or ok[i:].all()):
            return i
    return None


def initial_gor(values: np.ndarray) -> float:
    """Robust initial GOR: the median of the first three flowing values."""
    v = np.asarray(values, float)
    v = v[v > 0]
    return float(np.median(v[:3])) if v.size else float("nan")
