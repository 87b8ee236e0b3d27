"""The measured history as a fixed list of rows with a noise level, and the whitened residuals
of simulated responses against it.

:class:`ObservationSet` holds each row's ``sigma``: the data's own ``sigma`` column when given,
else the case's ``[noise]`` statement (:mod:`hmcore.model.noise_section`), else an estimate from
the data (:func:`hmcore.scoring.noise.fit_noise`), never below a floor that would hide the signal;
and a time correlation ``rho`` per quantity (stated, or estimated with the levels). It turns
simulated responses into the *whitened residual vector* used by the least-squares fits and the
attribution: ``z = (simulated - observed) / sigma`` along each well's series of one quantity,
then AR(1)-prewhitened, ``e_t = (z_t - rho z_{t-1}) / sqrt(1 - rho^2)``, so that pure noise
gives independent unit-variance entries and sums of squares are chi-square numbers.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from hmcore.model.case import HELD_BACK_FRACTION, default_history_end
from hmcore.model.noise_section import NoiseSection
from hmcore.scoring.alignment import nearest
from hmcore.scoring.noise import RESPONSE_OF
from hmcore.scoring.noise_fill import fill_sigma


# ============================================================================ observation set
@dataclass
class ObservationSet:
    """Measured rows with noise levels; maps simulated responses to (whitened) residuals.

    ``rows`` columns: well, quantity, response, days, observed, sigma, sigma_source (given,
    stated, estimated, pooled, default, floor, rate, propagated), flowing, derived, period
    ("fit" or "heldout"), in_vector (used in the whitened vector: measured, non-derived rows;
    GOR and WCT only while flowing), series (an integer per well and quantity). ``rho`` maps
    quantity -> noise time correlation, ``rho_well`` quantity -> well -> a well's own (stated)
    one. ``segment`` names each row's noise segment (flowing / shut_in for BHP, before / after
    breakthrough for GOR and WCT, all for rates; '' for derived rows). ``noise_report`` says
    per quantity how each level was set and which wells' series are uninformative.
    """

    rows: pd.DataFrame
    rho: dict[str, float]
    tolerance_days: float
    history_end_days: float | None
    noise_report: dict = field(default_factory=dict)
    rho_well: dict[str, dict[str, float]] = field(default_factory=dict)
    segment: tuple[str, ...] = ()
    statement: NoiseSection | None = None
    _whitening: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_case(cls, case, heldout_fraction: float = HELD_BACK_FRACTION) -> ObservationSet:
        """Rows of ``case.informative`` (all but history-controlled ones); held back after
        ``case.history_end_days`` or, when the case sets none, the last ``heldout_fraction``
        of the record. The case's ``[noise]`` statements (``case.noise``) come before the
        estimate; all of ``case.observed`` (the controlled rates too) marks where the signal
        jumps (shut-ins, rate changes).

        Missing sigma is first estimated from the observed series themselves;
        :meth:`refine` re-estimates it from the residuals of a calibrated model, where the
        simulator has taken the signal out."""
        obs = case.informative  # rows a history control fixes tell nothing
        end = case.history_end_days
        if end is None:
            end = default_history_end(obs.days.min(), obs.days.max(), heldout_fraction)
        return cls.from_observed(obs, end, case.time_tolerance_days,
                                 noise=getattr(case, "noise", None), context=case.observed)

    @classmethod
    def from_observed(cls, observed: pd.DataFrame, history_end_days: float,
                      tolerance_days: float = 30.0, responses: pd.DataFrame | None = None,
                      noise: NoiseSection | None = None, context: pd.DataFrame | None = None,
                      simulated: np.ndarray | None = None) -> ObservationSet:
        """See :meth:`from_case`; with ``responses`` the noise (sigma where neither the data
        nor ``noise`` give one, and rho unless stated) is estimated from the residual series
        ``simulated - observed``. ``simulated``: instead of ``responses``, the simulated value
        of every row in the order of the rows made from ``observed`` (what :meth:`simulated`
        of such a set returns). ``context``: observed rows (default ``observed``) whose
        flowing flags and oil rates mark the runs of continuous signal."""
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
        if simulated is not None:
            simulated = np.asarray(simulated, float)
            if simulated.shape != (len(df),):
                raise ValueError(f"{simulated.size} simulated values for {len(df)} rows")
            resid = simulated - df.observed.to_numpy(float)
        elif responses is not None:
            probe = cls(df.assign(in_vector=False), {}, float(tolerance_days),
                        float(history_end_days))
            resid = probe.simulated(responses) - df.observed.to_numpy(float)
        filled = fill_sigma(df, resid, noise, observed if context is None else context)
        _propagate_derived(df)
        measured = ~df.derived
        inflow = df.flowing | ~df.quantity.isin(["WGOR", "WWCT"])
        df["in_vector"] = measured & inflow & df.sigma.gt(0) & np.isfinite(df.sigma)
        cols = ["well", "quantity", "response", "days", "observed", "sigma", "sigma_source",
                "flowing", "derived", "period", "in_vector", "series"]
        return cls(df[cols].reset_index(drop=True), filled.rho, float(tolerance_days),
                   float(history_end_days), filled.report, filled.rho_well,
                   tuple(filled.segment), noise)

    def refine(self, responses: pd.DataFrame, observed: pd.DataFrame) -> ObservationSet:
        """The same rows with the noise re-estimated from the residuals of ``responses``
        (stated noise stays as stated)."""
        return ObservationSet.from_observed(observed, self.history_end_days,
                                            self.tolerance_days, responses, self.statement)

    def refine_simulated(self, simulated: np.ndarray, observed: pd.DataFrame,
                         context: pd.DataFrame | None = None) -> ObservationSet:
        """:meth:`refine` from the simulated value of every row (:meth:`simulated` of a run):
        what a campaign keeps of each call, so that the refined noise is a function of its
        journal. ``observed`` must be the frame this set was made from."""
        return ObservationSet.from_observed(observed, self.history_end_days,
                                            self.tolerance_days, noise=self.statement,
                                            context=context, simulated=simulated)

    def without_time_correlation(self) -> ObservationSet:
        """A copy that whitens by sigma only (rho = 0): plain weighted least squares."""
        return dataclasses.replace(self, rho={q: 0.0 for q in self.rho}, rho_well={})

    @property
    def uninformative(self) -> set[tuple[str, str]]:
        """(quantity, well) pairs whose whole fitted series lies within the noise floor of
        zero (a water cut of 3e-5 against a floor of 0.01): no floor is put above them, and
        the noise table says so."""
        return {(q, w) for q, entry in self.noise_report.items()
                for w in entry.get("uninformative", [])}

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

    def row_rho(self, idx: np.ndarray) -> np.ndarray:
        """The AR(1) correlation of rows ``idx``: a well's own where stated, else its
        quantity's."""
        q = self.rows.quantity.to_numpy()[idx]
        w = self.rows.well.to_numpy()[idx]
        return np.array([self.rho_well.get(a, {}).get(b, self.rho.get(a, 0.0))
                         for a, b in zip(q, w)], float)

    def whiten(self, z: np.ndarray, period: str = "fit") -> np.ndarray:
        """AR(1)-prewhitened residual vector of ``period`` from standardized residuals ``z``
        (unmatched rows count as 0: the vector has a fixed length for a given set)."""
        idx, k, rho, scale = self._whitening_of(period)
        zz = np.nan_to_num(np.asarray(z, float)[idx], nan=0.0)
        out = zz.copy()
        out[k] = (zz[k] - rho * zz[k - 1]) / scale
        return out

    def _whitening_of(self, period: str) -> tuple[np.ndarray, ...]:
        """(rows of ``period``'s vector, the positions that follow a row of their own series
        with rho > 0, their rho, sqrt(1 - rho^2)); computed once per period."""
        if period not in self._whitening:
            idx = self.vector_index(period)
            series = self.rows.series.to_numpy()[idx]
            rhos = self.row_rho(idx)
            start = np.r_[True, series[1:] != series[:-1]] if len(idx) else np.zeros(0, bool)
            k = np.flatnonzero(~start & (rhos > 0))
            rho = rhos[k]
            self._whitening[period] = (idx, k, rho, np.sqrt(1.0 - rho * rho))
        return self._whitening[period]

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


def _propagate_derived(df: pd.DataFrame) -> None:
    """Sigma of derived WWPR / WGPR rows from the WCT / GOR sigma on the same day: for water
    ``oil * s_wct / max(1 - wct, 0.05)^2``, for gas ``oil * s_gor``. A row whose oil rate, water
    cut or GOR is missing that day, or given twice, keeps no sigma."""
    der = (df.derived & df.sigma.isna()).to_numpy()
    if not der.any():
        return
    rows = df[der]
    at = pd.MultiIndex.from_arrays([rows.well, rows.days])

    def lookup(q: str, col: str) -> np.ndarray:
        sub = df[df.quantity == q]
        sub = sub[~sub.duplicated(["well", "days"], keep=False)]
        return sub.set_index(["well", "days"])[col].reindex(at).to_numpy(float)

    oil = lookup("WOPR", "observed")
    water = rows.quantity.to_numpy() == "WWPR"
    wct = lookup("WWCT", "observed")
    sigma = np.where(water, oil * lookup("WWCT", "sigma") / np.maximum(1.0 - wct, 0.05) ** 2,
                     oil * lookup("WGOR", "sigma"))
    ok = np.isfinite(sigma) & (sigma > 0)
    idx = rows.index[ok]
    df.loc[idx, "sigma"] = sigma[ok]
    df.loc[idx, "sigma_source"] = "propagated"
