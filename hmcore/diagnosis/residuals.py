"""Residual analysis of a calibrated case, measured against the noise level.

Two things live here:

* :class:`ObservationSet` - the measured history as a fixed list of rows with a noise level
  (``sigma`` from the data when given, otherwise estimated robustly, see
  :func:`estimate_noise`) and a time correlation ``rho`` per quantity. It turns simulated
  responses into the *whitened residual vector* used by the recalibration and the attribution:
  ``z = (simulated - observed) / sigma`` along each well's series of one quantity, then
  AR(1)-prewhitened, ``e_t = (z_t - rho z_{t-1}) / sqrt(1 - rho^2)``, so that pure noise gives
  independent unit-variance entries and sums of squares are chi-square numbers.
* :func:`analyse_residuals` - per well, response (bhp, oil, water, gas, gor, wct) and period
  (fitted history, its early and late halves, the held-back part, and flowing vs shut-in for
  BHP): bias, trend, RMS, all standardised by the noise level, with "beyond noise" flags that
  account for the autocorrelation (effective sample size ``n (1 - rho) / (1 + rho)``), and the
  water (WWCT crossing 0.05, see :data:`WATER_BREAKTHROUGH_SEEN`) and gas (GOR 20 % above
  its initial value) breakthrough timing errors. The result is a JSON-serialisable dict.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from hmcore.alignment import nearest
from hmcore.synthetic import PUNQ_NOISE, WATER_BREAKTHROUGH_WCT

RESPONSE_OF = {"WBHP": "bhp", "WOPR": "oil", "WWPR": "water", "WGPR": "gas", "WGOR": "gor",
               "WWCT": "wct"}

SIGMA_FLOOR = {"WBHP": 0.3, "WWCT": 0.01, "WGOR_REL": 0.03, "RATE_REL": 0.02}
"""Smallest noise level an estimate may give: bar, fraction, relative GOR, relative rate."""
AFTER_BREAKTHROUGH_DEFAULT = {"WWCT": PUNQ_NOISE.wct_after, "WGOR": PUNQ_NOISE.gor_after}
"""Noise after water / gas breakthrough when no well's record allows an estimate: typical
test-separator uncertainty, PUNQ-S3's description (WCT 0.05, GOR 25 %; see
:class:`hmcore.synthetic.NoiseModel`)."""
OIL_RATE_SIGMA_REL = 0.05
"""Noise of a measured oil rate without sigma (usually the rate control): 5 % of the value."""
OIL_RATE_SIGMA_MIN = 1.0
BREAKTHROUGH_SIGMAS = 2.0
WATER_BREAKTHROUGH_SEEN = WATER_BREAKTHROUGH_WCT + BREAKTHROUGH_SIGMAS * PUNQ_NOISE.wct_before
"""Water breakthrough as the diagnosis sees it in a noisy record: the water cut reaches
:data:`hmcore.synthetic.WATER_BREAKTHROUGH_WCT` (0.01, the one threshold) by
``BREAKTHROUGH_SIGMAS`` standard deviations of the noise before breakthrough (0.02): 0.05.
A measured water cut of 0.01 is within the noise of a dry well (1 sigma of 0.02 is 0.02)."""
GAS_BREAKTHROUGH_RATIO = 1.2
"""Gas breakthrough as the diagnosis sees it: the GOR 20 % above the well's initial one. The
synthetic history's threshold is 1.10 (:data:`hmcore.synthetic.GAS_BREAKTHROUGH_GOR_RATIO`);
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


def _breakthrough_index(values: np.ndarray, threshold: float, persist: int = 2) -> int | None:
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


# ============================================================================ observation set
@dataclass
class ObservationSet:
    """Measured rows with noise levels; maps simulated responses to (whitened) residuals.

    ``rows`` columns: well, quantity, response, days, observed, sigma, sigma_source (given,
    estimated, floor, rate), flowing, derived, period ("fit" or "heldout"), in_vector (used in
    the whitened vector: measured, non-derived rows; GOR and WCT only while flowing), series
    (an integer per well and quantity). ``rho`` maps quantity -> noise time correlation.
    """

    rows: pd.DataFrame
    rho: dict[str, float]
    tolerance_days: float
    history_end_days: float | None
    noise_report: dict = field(default_factory=dict)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_case(cls, case, heldout_fraction: float = 0.25) -> "ObservationSet":
        """Rows of ``case.informative`` (all but history-controlled ones); held back after ``case.history_end_days`` or, when the
        case sets none, the last ``heldout_fraction`` of the record.

        Missing sigma is first estimated from the observed series themselves (signal changes
        inflate it: a conservative start); :meth:`refine` re-estimates it from the residuals
        of a calibrated model, where the simulator has taken the signal out."""
        obs = case.informative  # rows a history control fixes tell nothing
        end = case.history_end_days
        if end is None:
            d0, d1 = float(obs.days.min()), float(obs.days.max())
            end = d0 + (1.0 - heldout_fraction) * (d1 - d0)
        return cls.from_observed(obs, end, case.time_tolerance_days)

    @classmethod
    def from_observed(cls, observed: pd.DataFrame, history_end_days: float,
                      tolerance_days: float = 30.0, responses: pd.DataFrame | None = None
                      ) -> "ObservationSet":
        """See :meth:`from_case`; with ``responses`` the noise (sigma where the data give
        none, and rho always) is estimated from the residual series ``simulated - observed``."""
        df = observed.copy()
        if "sigma" not in df:
            df["sigma"] = np.nan
        if "flowing" not in df:
            df["flowing"] = True
        if "derived" not in df:
            df["derived"] = False
        df = df.rename(columns={"value": "observed"})
        df = df[df.quantity.isin(list(RESPONSE_OF))].copy()
        df["response"] = df.quantity.map(RESPONSE_OF)
        df["period"] = np.where(df.days <= history_end_days + 1e-9, "fit", "heldout")
        df = df.sort_values(["well", "quantity", "days"], kind="stable").reset_index(drop=True)
        df["series"] = df.groupby(["well", "quantity"], sort=False).ngroup()
        df["sigma_source"] = np.where(df.sigma.notna(), "given", "")
        df["flowing"] = df.flowing.astype(bool)
        df["derived"] = df.derived.astype(bool)
        resid = None
        if responses is not None:
            probe = cls(df.assign(in_vector=False), {}, float(tolerance_days),
                        float(history_end_days))
            resid = probe.simulated(responses) - df.observed.to_numpy(float)
        rho, report = _fill_sigma(df, resid)
        _propagate_derived(df)
        measured = ~df.derived
        inflow = df.flowing | ~df.quantity.isin(["WGOR", "WWCT"])
        df["in_vector"] = measured & inflow & df.sigma.gt(0) & np.isfinite(df.sigma)
        cols = ["well", "quantity", "response", "days", "observed", "sigma", "sigma_source",
                "flowing", "derived", "period", "in_vector", "series"]
        return cls(df[cols].reset_index(drop=True), rho, float(tolerance_days),
                   float(history_end_days), report)

    def refine(self, responses: pd.DataFrame, observed: pd.DataFrame) -> "ObservationSet":
        """The same rows with the noise re-estimated from the residuals of ``responses``."""
        return ObservationSet.from_observed(observed, self.history_end_days,
                                            self.tolerance_days, responses)

    def without_time_correlation(self) -> "ObservationSet":
        """A copy that whitens by sigma only (rho = 0): plain weighted least squares."""
        return dataclasses.replace(self, rho={q: 0.0 for q in self.rho})

    # ---------------------------------------------------------------- simulated values
    def simulated(self, responses: pd.DataFrame) -> np.ndarray:
        """Simulated value of every row (nearest simulated time within the tolerance, see
        :func:`hmcore.alignment.nearest`; NaN when there is none)."""
        if responses is None or len(responses) == 0:
            return np.full(len(self.rows), np.nan)
        return nearest(self.rows, responses, self.tolerance_days).value

    def standardized(self, responses: pd.DataFrame) -> np.ndarray:
        """``(simulated - observed) / sigma`` per row (NaN where unmatched or no sigma)."""
        return (self.simulated(responses) - self.rows.observed.to_numpy(float)) / \
            self.rows.sigma.to_numpy(float)

    def vector_index(self, period: str) -> np.ndarray:
        mask = self.rows.in_vector.to_numpy() & (self.rows.period.to_numpy() == period)
        return np.flatnonzero(mask)

    def whiten(self, z: np.ndarray, period: str = "fit") -> np.ndarray:
        """AR(1)-prewhitened residual vector of ``period`` from standardized residuals ``z``
        (unmatched rows count as 0: the vector has a fixed length for a given set)."""
        idx = self.vector_index(period)
        zz = np.nan_to_num(np.asarray(z, float)[idx], nan=0.0)
        rows = self.rows.iloc[idx]
        out = np.empty_like(zz)
        series = rows.series.to_numpy()
        quantity = rows.quantity.to_numpy()
        start = np.r_[True, series[1:] != series[:-1]]
        for k in range(len(zz)):
            rho = self.rho.get(quantity[k], 0.0)
            if start[k] or rho <= 0:
                out[k] = zz[k]
            else:
                out[k] = (zz[k] - rho * zz[k - 1]) / math.sqrt(1.0 - rho * rho)
        return out

    def residual_vector(self, responses: pd.DataFrame, period: str = "fit") -> np.ndarray:
        return self.whiten(self.standardized(responses), period)

    @property
    def n_fit(self) -> int:
        return len(self.vector_index("fit"))

    @property
    def n_heldout(self) -> int:
        return len(self.vector_index("heldout"))

    def n_noise(self, period: str = "fit") -> int:
        """Points of ``period`` whose whitened residual is measurement noise: the vector's
        length less the rate controls (sigma from the rate), whose residual is 0 while the well
        makes its rate. The chi-square mean of a model that fits ``period`` within noise."""
        idx = self.vector_index(period)
        return int(np.count_nonzero(self.rows.sigma_source.to_numpy()[idx] != "rate"))


def _segments(df: pd.DataFrame, q: str) -> list[tuple[str, pd.Index]]:
    """Noise segments of quantity ``q``: parts of each well's series with one noise level."""
    out = []
    sub = df[(df.quantity == q) & ~df.derived]
    for well, g in sub.groupby("well", sort=False):
        if q == "WBHP":
            out.append(("flowing", g.index[g.flowing.to_numpy()]))
            out.append(("shut_in", g.index[~g.flowing.to_numpy()]))
        elif q in ("WGOR", "WWCT"):
            f = g[g.flowing]
            v = f.observed.to_numpy(float)
            if q == "WGOR":
                bt = _breakthrough_index(v, GAS_BREAKTHROUGH_RATIO * initial_gor(v))
            else:
                bt = _breakthrough_index(v, WATER_BREAKTHROUGH_SEEN)
            bt = len(v) if bt is None else bt
            out.append(("before", f.index[:bt]))
            out.append(("after", f.index[bt:]))
        else:
            out.append(("all", g.index))
    return out


def _fill_sigma(df: pd.DataFrame, resid: np.ndarray | None = None
                ) -> tuple[dict[str, float], dict]:
    """Fill missing sigma by robust estimation; return rho per quantity and a report.

    ``resid`` (simulated - observed per row, optional): estimate from the residual series
    instead of the observed ones. Only rows of the fitted period are used (the held-back
    data must not set their own noise level). A segment too short to estimate takes the
    median of its kind in the other wells; an after-breakthrough segment that no well can
    estimate takes :data:`AFTER_BREAKTHROUGH_DEFAULT` (and never less than the well's own
    level before breakthrough); a shut-in BHP segment with no estimate the flowing level.
    """
    rho: dict[str, float] = {}
    report: dict = {}
    source_of = "residuals" if resid is not None else "observed series"
    for q in ("WBHP", "WGOR", "WWCT", "WOPR", "WWPR", "WGPR"):
        segs = _segments(df, q)
        if not segs:
            continue
        given = all(df.loc[idx, "sigma"].notna().all() for _, idx in segs)
        if q == "WOPR" and not given:
            v = df.loc[df.quantity == q, "observed"].abs()
            miss = (df.quantity == q) & df.sigma.isna() & ~df.derived
            df.loc[miss, "sigma"] = np.maximum(OIL_RATE_SIGMA_REL * v[miss], OIL_RATE_SIGMA_MIN)
            df.loc[miss, "sigma_source"] = "rate"
            rho[q] = 0.0
            report[q] = {"sigma": f"{OIL_RATE_SIGMA_REL:.0%} of the rate (rate control)",
                         "rho": 0.0}
            continue
        rel = q in ("WGOR", "WWPR", "WGPR")
        series, keys = [], []
        for kind, idx_all in segs:
            idx = idx_all[(df.loc[idx_all, "period"] == "fit").to_numpy()]
            obs = df.loc[idx, "observed"].to_numpy(float)
            if resid is not None:
                r = resid[np.asarray(idx, int)]
                if rel:
                    r = np.log(np.maximum(obs + r, 1e-9)) - np.log(np.maximum(obs, 1e-9))
                v = r[np.isfinite(r)]
            else:
                v = np.log(np.maximum(obs, 1e-9)) if rel else obs
            if given:
                sig = df.loc[idx, "sigma"].to_numpy(float)
                if resid is not None:
                    r = resid[np.asarray(idx, int)]
                    v = (r / sig)[np.isfinite(r)]
                else:
                    v = obs / sig
            series.append(v)
            keys.append((kind, idx_all))
        sig, r = estimate_noise(series)
        rho[q] = min(max(r, 0.0), MAX_RHO)
        entry: dict = {"rho": rho[q], "sigma_given": bool(given), "estimated_from": source_of}
        if not given:
            floor = {"WBHP": SIGMA_FLOOR["WBHP"], "WWCT": SIGMA_FLOOR["WWCT"]}.get(
                q, SIGMA_FLOOR["WGOR_REL"] if q == "WGOR" else SIGMA_FLOOR["RATE_REL"])
            fallback: dict[str, list[float]] = {}
            for (kind, idx), s in zip(keys, sig):
                if math.isfinite(s):
                    fallback.setdefault(kind, []).append(s)
            levels = []
            own_before: dict[str, float] = {}
            for (kind, idx), s in zip(keys, sig):
                if not len(idx):
                    continue
                well = df.loc[idx[0], "well"]
                source = "estimated"
                if not math.isfinite(s):  # too short to estimate
                    source = "pooled"
                    if fallback.get(kind):
                        s = float(np.median(fallback[kind]))
                    elif kind == "after" and q in AFTER_BREAKTHROUGH_DEFAULT:
                        s, source = AFTER_BREAKTHROUGH_DEFAULT[q], "default"
                    elif kind == "shut_in" and fallback.get("flowing"):
                        s = float(np.median(fallback["flowing"]))
                    else:
                        pool = [x for v in fallback.values() for x in v]
                        s = float(np.median(pool)) if pool else floor
                if kind == "before":
                    own_before[well] = s
                elif kind == "after" and well in own_before and s < own_before[well]:
                    s = own_before[well]
                if s < floor:
                    s, source = floor, "floor"
                if rel:
                    sigma = s * np.abs(df.loc[idx, "observed"].to_numpy(float))
                    sigma = np.maximum(sigma, 1e-6)
                else:
                    sigma = np.full(len(idx), s)
                miss = df.loc[idx, "sigma"].isna().to_numpy()
                df.loc[idx[miss], "sigma"] = sigma[miss]
                df.loc[idx[miss], "sigma_source"] = source
                levels.append({"segment": kind, "sigma": s, "relative": rel, "n": int(len(idx))})
            entry["levels"] = levels
        report[q] = entry
    return rho, report


def _propagate_derived(df: pd.DataFrame) -> None:
    """Sigma of derived WWPR / WGPR rows from the WCT / GOR sigma on the same day."""
    der = df.derived & df.sigma.isna()
    if not der.any():
        return
    key = df.set_index(["well", "days", "quantity"])
    for i in np.flatnonzero(der.to_numpy()):
        row = df.iloc[i]
        try:
            oil = float(key.loc[(row.well, row.days, "WOPR"), "observed"])
            if row.quantity == "WWPR":
                wct = float(key.loc[(row.well, row.days, "WWCT"), "observed"])
                s = float(key.loc[(row.well, row.days, "WWCT"), "sigma"])
                sigma = oil * s / max(1.0 - wct, 0.05) ** 2
            else:
                s = float(key.loc[(row.well, row.days, "WGOR"), "sigma"])
                sigma = oil * s
        except (KeyError, TypeError):
            continue
        if math.isfinite(sigma) and sigma > 0:
            df.iat[i, df.columns.get_loc("sigma")] = sigma
            df.iat[i, df.columns.get_loc("sigma_source")] = "propagated"


# ============================================================================ analysis
def _stats(days: np.ndarray, z: np.ndarray, resid: np.ndarray, rho: float) -> dict:
    """Bias, trend and RMS of standardized residuals ``z`` (and raw residuals ``resid``)."""
    ok = np.isfinite(z)
    days, z, resid = days[ok], z[ok], resid[ok]
    n = int(z.size)
    if n == 0:
        return {"n": 0}
    infl = (1.0 + rho) / (1.0 - rho)
    n_eff = max(n / infl, 1.0)
    bias = float(np.mean(z))
    out = {"n": n, "n_eff": n_eff, "first_day": float(days.min()), "last_day": float(days.max()),
           "bias": float(np.mean(resid)), "bias_std": bias,
           "z_bias": bias * math.sqrt(n_eff), "rms_std": float(np.sqrt(np.mean(z ** 2))),
           "rms": float(np.sqrt(np.mean(resid ** 2))), "trend_std_per_year": 0.0, "z_trend": 0.0,
           "trend_per_year": 0.0}
    t = days / 365.25
    sxx = float(np.sum((t - t.mean()) ** 2))
    if n >= 4 and sxx > 0:
        slope = float(np.sum((t - t.mean()) * (z - bias)) / sxx)
        slope_raw = float(np.sum((t - t.mean()) * (resid - resid.mean())) / sxx)
        se = math.sqrt(infl / sxx)
        out.update(trend_std_per_year=slope, trend_per_year=slope_raw, z_trend=slope / se)
    out["beyond_noise"] = bool(abs(out["z_bias"]) > Z_BEYOND_NOISE
                               or abs(out["z_trend"]) > Z_BEYOND_NOISE)
    return out


def _crossing_day(days: np.ndarray, values: np.ndarray, threshold: float,
                  persist: int = 2) -> float | None:
    i = _breakthrough_index(values, threshold, persist)
    return None if i is None else float(days[i])


def breakthrough_timing(obs_set: ObservationSet, responses: pd.DataFrame, well: str) -> dict:
    """Water (WWCT >= 0.05) and gas (GOR >= 1.2 x initial) breakthrough: observed vs simulated
    day and the error (simulated - observed); beyond noise when the error exceeds twice the
    local spacing of the observations (or one of them breaks through and the other not)."""
    out = {}
    rows = obs_set.rows
    for kind, q in (("water", "WWCT"), ("gas", "WGOR")):
        o = rows[(rows.well == well) & (rows.quantity == q) & rows.flowing]
        if o.empty:
            continue
        od, ov = o.days.to_numpy(float), o.observed.to_numpy(float)
        s = responses[(responses.well == well) & (responses.quantity == q)].sort_values("days")
        sv = s.value.to_numpy(float)
        if q == "WGOR":
            sv = sv[sv > 0]
            thr_o = GAS_BREAKTHROUGH_RATIO * initial_gor(ov)
            thr_s = GAS_BREAKTHROUGH_RATIO * (initial_gor(sv) if sv.size else float("nan"))
            # the simulated series is read at the observation days (same sampling)
            sv_at = obs_set.simulated(responses)[o.index.to_numpy()]
            t_obs = _crossing_day(od, ov, thr_o)
            t_sim = _crossing_day(od, sv_at, thr_s) if np.isfinite(thr_s) else None
            threshold = f"GOR >= {GAS_BREAKTHROUGH_RATIO:g} x initial"
        else:
            sv_at = obs_set.simulated(responses)[o.index.to_numpy()]
            t_obs = _crossing_day(od, ov, WATER_BREAKTHROUGH_SEEN)
            t_sim = _crossing_day(od, sv_at, WATER_BREAKTHROUGH_SEEN)
            threshold = f"WWCT >= {WATER_BREAKTHROUGH_SEEN:g}"
        ref = t_obs if t_obs is not None else t_sim
        if ref is not None and od.size > 1:
            k = int(np.clip(np.searchsorted(od, ref), 1, od.size - 1))
            spacing = float(od[k] - od[k - 1])
        else:
            spacing = float(np.median(np.diff(od))) if od.size > 1 else 30.0
        tol = max(2.0 * spacing, 45.0)
        entry = {"threshold": threshold, "observed_day": t_obs, "simulated_day": t_sim,
                 "error_days": None, "tolerance_days": tol, "beyond_noise": False}
        if t_obs is not None and t_sim is not None:
            entry["error_days"] = t_sim - t_obs
            entry["beyond_noise"] = abs(t_sim - t_obs) > tol
        elif (t_obs is None) != (t_sim is None):
            entry["beyond_noise"] = True
            entry["note"] = ("observed breakthrough the model does not reproduce" if t_sim is None
                             else "simulated breakthrough that is not observed")
        out[kind] = entry
    return out


def analyse_residuals(obs_set: ObservationSet, responses: pd.DataFrame) -> dict:
    """Residual statistics per well, response and period, and breakthrough timing errors.

    Returns ``{"wells": {well: {response: {period: stats}}, "breakthrough": {well: ...},
    "flags": [...], "summary": {...}}`` where stats hold n, n_eff, bias (data units),
    bias_std, z_bias, trend (per year), z_trend, rms, rms_std and beyond_noise; periods are
    fit, early, late, heldout and (bhp) flowing, shut_in.
    """
    rows = obs_set.rows
    sim = obs_set.simulated(responses)
    resid = sim - rows.observed.to_numpy(float)
    z = resid / rows.sigma.to_numpy(float)
    fit_days = rows.days[rows.period == "fit"]
    mid = float(fit_days.min() + (fit_days.max() - fit_days.min()) / 2.0) if len(fit_days) else 0.0
    wells: dict = {}
    flags: list[dict] = []
    for (well, q), g in rows.groupby(["well", "quantity"], sort=True):
        resp = RESPONSE_OF[q]
        idx = g.index.to_numpy()
        if q in ("WGOR", "WWCT", "WWPR", "WGPR"):
            idx = idx[g.flowing.to_numpy()]
        rho = obs_set.rho.get(q, obs_set.rho.get("WWCT" if q == "WWPR" else "WGOR", 0.0))
        d = rows.days.to_numpy(float)
        per = rows.period.to_numpy()
        flowing = rows.flowing.to_numpy()
        periods = {"fit": idx[per[idx] == "fit"]}
        periods["early"] = periods["fit"][d[periods["fit"]] <= mid]
        periods["late"] = periods["fit"][d[periods["fit"]] > mid]
        periods["heldout"] = idx[per[idx] == "heldout"]
        if q == "WBHP":
            periods["flowing"] = periods["fit"][flowing[periods["fit"]]]
            periods["shut_in"] = periods["fit"][~flowing[periods["fit"]]]
        entry = {}
        for name, pidx in periods.items():
            if len(pidx) == 0:
                continue
            st = _stats(d[pidx], z[pidx], resid[pidx], rho)
            if st.get("n", 0) == 0:
                continue
            entry[name] = st
            if st.get("beyond_noise") and name != "heldout":
                flags.append({"well": well, "response": resp, "period": name,
                              "z_bias": st["z_bias"], "z_trend": st["z_trend"],
                              "text": _flag_text(well, resp, name, st)})
        wells.setdefault(well, {})[resp] = entry
    timing = {}
    for well in sorted(rows.well.unique()):
        bt = breakthrough_timing(obs_set, responses, well)
        if bt:
            timing[well] = bt
            for kind, e in bt.items():
                if e["beyond_noise"]:
                    flags.append({"well": well, "response": f"{kind}_breakthrough",
                                  "period": "fit", "error_days": e["error_days"],
                                  "text": _timing_text(well, kind, e)})
    rf = obs_set.residual_vector(responses, "fit")
    rh = obs_set.residual_vector(responses, "heldout") if obs_set.n_heldout else np.zeros(0)
    m_fit, m_ho = obs_set.n_noise("fit"), obs_set.n_noise("heldout")
    summary = {"n_fit": int(rf.size), "ssr_fit": float(rf @ rf), "n_fit_measured": m_fit,
               "chi2_per_measured_point_fit": float(rf @ rf / max(m_fit, 1)),
               "n_heldout": int(rh.size), "ssr_heldout": float(rh @ rh),
               "n_heldout_measured": m_ho,
               "chi2_per_measured_point_heldout": float(rh @ rh / m_ho) if m_ho else None,
               "n_flags": len(flags), "history_end_days": obs_set.history_end_days}
    return {"wells": wells, "breakthrough": timing, "flags": flags, "summary": summary,
            "noise": {"rho": obs_set.rho, "estimation": obs_set.noise_report}}


def _flag_text(well: str, resp: str, period: str, st: dict) -> str:
    parts = []
    if abs(st["z_bias"]) > Z_BEYOND_NOISE:
        parts.append(f"the model is {'above' if st['bias'] > 0 else 'below'} the data by "
                     f"{abs(st['bias']):.3g} on average ({abs(st['bias_std']):.2f} sigma, "
                     f"z = {st['z_bias']:+.1f})")
    if abs(st["z_trend"]) > Z_BEYOND_NOISE:
        parts.append(f"the misfit drifts by {st['trend_per_year']:+.3g} per year "
                     f"(z = {st['z_trend']:+.1f})")
    return f"{well} {resp} ({period}): " + "; ".join(parts)


def _timing_text(well: str, kind: str, e: dict) -> str:
    if e.get("error_days") is None:
        return f"{well} {kind} breakthrough: {e.get('note')}"
    return (f"{well} {kind} breakthrough {'late' if e['error_days'] > 0 else 'early'} by "
            f"{abs(e['error_days']):.0f} days (observed day {e['observed_day']:.0f}, "
            f"simulated day {e['simulated_day']:.0f})")
