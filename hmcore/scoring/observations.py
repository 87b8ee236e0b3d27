"""The measured history as a fixed list of rows with a noise level, and the whitened residuals
of simulated responses against it.

:class:`ObservationSet` holds ``sigma`` from the data when given, otherwise estimated robustly
(:func:`hmcore.scoring.noise.estimate_noise`), and a time correlation ``rho`` per quantity. It
turns simulated responses into the *whitened residual vector* used by the least-squares fits and
the attribution: ``z = (simulated - observed) / sigma`` along each well's series of one
quantity, then AR(1)-prewhitened, ``e_t = (z_t - rho z_{t-1}) / sqrt(1 - rho^2)``, so that pure
noise gives independent unit-variance entries and sums of squares are chi-square numbers.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from hmcore.model.case import HELD_BACK_FRACTION, default_history_end
from hmcore.scoring.alignment import nearest
from hmcore.scoring.noise import (
    AFTER_BREAKTHROUGH_DEFAULT,
    GAS_BREAKTHROUGH_RATIO,
    MAX_RHO,
    OIL_RATE_SIGMA_MIN,
    OIL_RATE_SIGMA_REL,
    RESPONSE_OF,
    SIGMA_FLOOR,
    WATER_BREAKTHROUGH_SEEN,
    breakthrough_index,
    estimate_noise,
    initial_gor,
)


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
    def from_case(cls, case, heldout_fraction: float = HELD_BACK_FRACTION) -> "ObservationSet":
        """Rows of ``case.informative`` (all but history-controlled ones); held back after ``case.history_end_days`` or, when the
        case sets none, the last ``heldout_fraction`` of the record.

        Missing sigma is first estimated from the observed series themselves (signal changes
        inflate it: a conservative start); :meth:`refine` re-estimates it from the residuals
        of a calibrated model, where the simulator has taken the signal out."""
        obs = case.informative  # rows a history control fixes tell nothing
        end = case.history_end_days
        if end is None:
            end = default_history_end(obs.days.min(), obs.days.max(), heldout_fraction)
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
        :func:`hmcore.scoring.alignment.nearest`; NaN when there is none)."""
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
                bt = breakthrough_index(v, GAS_BREAKTHROUGH_RATIO * initial_gor(v))
            else:
                bt = breakthrough_index(v, WATER_BREAKTHROUGH_SEEN)
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
