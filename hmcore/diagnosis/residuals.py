"""Residual analysis of a calibrated case, measured against the noise level.

:func:`analyse_residuals`, against the noise level of
:class:`hmcore.scoring.observations.ObservationSet`: per well, response (bhp, oil, water, gas,
gor, wct) and period (fitted history, its early and late halves, the held-back part, and
flowing vs shut-in for BHP): bias, trend, RMS, all standardised by the noise level, with
"beyond noise" flags that account for the autocorrelation (effective sample size
``n (1 - rho) / (1 + rho)``), and the water (WWCT crossing 0.05, see
:data:`WATER_BREAKTHROUGH_SEEN`) and gas (GOR 20 % above its initial value) breakthrough timing
errors. The result is a JSON-serialisable dict.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from hmcore.scoring.noise import (GAS_BREAKTHROUGH_RATIO, RESPONSE_OF, WATER_BREAKTHROUGH_SEEN,
                                  Z_BEYOND_NOISE, breakthrough_index, initial_gor)
from hmcore.scoring.observations import ObservationSet


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
    i = breakthrough_index(values, threshold, persist)
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
