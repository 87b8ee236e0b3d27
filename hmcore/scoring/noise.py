"""Measurement noise: how it is described and how it is estimated from the data.

* :class:`NoiseModel` - the noise of a well's observed history as PUNQ-S3's description states
  it (BHP, GOR and water cut, before and after breakthrough, AR(1) in time). hmflow's
  generators draw their noise from it (:mod:`hmcore.scenarios.synthetic`,
  :mod:`hmcore.scenarios.hidden`); the estimator uses it as its default where a record allows
  no estimate.
* :func:`estimate_noise` - a robust noise level and AR(1) correlation from series without
  stated sigma (variogram of first differences), used by
  :class:`hmcore.scoring.observations.ObservationSet`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


SIGMA_FLOOR = {"WBHP": 0.3, "WWCT": 0.01, "WGOR_REL": 0.03, "RATE_REL": 0.02}
"""Smallest noise level an estimate may give: bar, fraction, relative GOR, relative rate."""


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


def estimate_noise(series: list[np.ndarray], rho: float | None = None
                   ) -> tuple[list[float], float]:
    """Noise level of each series and one shared lag-1 correlation, from robust variograms.

    Model: observation = smooth signal + sigma_s * AR(1) noise with correlation ``rho``, so the
    noise part of the variogram is ``sigma_s^2 (1 - rho^h)`` and ``gamma(2) / gamma(1) =
    1 + rho``. ``rho`` (unless given) is that ratio pooled over the series (each weighted by
    its length, on its own scale); ``sigma_s^2 = (gamma(1) + gamma(2)) / ((1 - rho) +
    (1 - rho^2))``. Only lags 1 and 2 are used: a smooth misfit left in a series adds
    ``c h^2`` to the variogram and biases the estimate less the shorter the lags. Series
    shorter than 5 get NaN (no estimate).
    """
    grams = [robust_variogram(s, 2) if len(s) >= 5 else np.full(2, np.nan) for s in series]
    if rho is None:
        num = den = 0.0
        for s, g in zip(series, grams):
            if np.isfinite(g).all() and g.sum() > 0:
                num += len(s) * g[1] / g.sum()
                den += len(s) * g[0] / g.sum()
        rho = num / den - 1.0 if den > 0 else 0.0
    rho = float(min(max(rho, 0.0), MAX_RHO))
    sig = []
    for g in grams:
        if np.isfinite(g).all():
            sig.append(math.sqrt(max(g.sum() / ((1.0 - rho) + (1.0 - rho * rho)), 0.0)))
        else:
            sig.append(float("nan"))
    return sig, rho


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
