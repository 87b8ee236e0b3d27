"""How each row of an :class:`hmcore.scoring.observations.ObservationSet` gets its noise level.

Per quantity, in order of precedence: the data's own ``sigma``; the case's ``[noise]``
statement (:mod:`hmcore.model.noise_section`); an estimate from the data
(:func:`hmcore.scoring.noise.fit_noise`) per well and noise segment (BHP flowing / shut in, GOR
and water cut before / after breakthrough, rates), from the rows of the fitted period, with the
signal's runs cut where a well shuts in, reopens or changes its rate; a fallback where a segment
cannot be estimated; and a floor, never above the signal it would hide.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from hmcore.model.noise_section import NoiseSection, QuantityNoise
from hmcore.scoring.noise import (
    AFTER_BREAKTHROUGH_DEFAULT,
    FLOOR_SIGNAL_SHARE,
    GAS_BREAKTHROUGH_RATIO,
    MAX_RHO,
    OIL_RATE_SIGMA_MIN,
    OIL_RATE_SIGMA_REL,
    RATE_STEP,
    SHRINK_CONTRASTS,
    SIGMA_FLOOR,
    UNCERTAIN_FACTOR,
    WATER_BREAKTHROUGH_SEEN,
    NoiseFit,
    NoiseSeries,
    breakthrough_index,
    fit_noise,
    initial_gor,
    level_interval,
    variogram_rho,
)
from hmcore.scoring.noise_scale import (
    ABSOLUTE_NOISE,
    CENSORED_SHARE,
    RELATIVE_NOISE,
    NoiseScale,
    ScaleData,
    censored_sigma,
    choose_scale,
    smoothed_level,
)

# ============================================================================ noise segments
RELATIVE = ("WGOR", "WWPR", "WGPR")
"""Quantities whose noise is relative to the value unless the data say otherwise (estimated
on the logarithm)."""


SCALED = RELATIVE + ("WWCT",)
"""Quantities whose noise may grow with their level: the scale (absolute, relative, relative
with a minimum) is chosen from the data (:func:`hmcore.scoring.noise_scale.choose_scale`);
the water cut's default is absolute."""


QUIET = ("flowing", "before", "all")
"""Segments whose signal changes slowly: the correlation is estimated from them and not from
the water cut (a build-up, the rise after breakthrough and the growth of a water cut of 1e-5
mimic a correlation over a few rows; a dry well's water cut is clipped at 0)."""


@dataclass(frozen=True)
class _Segment:
    """Rows of one well and quantity with one noise level (``kind``)."""

    well: str
    kind: str
    idx: pd.Index


def _segments(df: pd.DataFrame, q: str) -> list[_Segment]:
    """Noise segments of quantity ``q``: BHP flowing / shut in, GOR and WCT before / after
    breakthrough (flowing rows only), rates all together; per well."""
    out = []
    sub = df[(df.quantity == q) & ~df.derived]
    for well, g in sub.groupby("well", sort=False):
        if q == "WBHP":
            out.append(_Segment(well, "flowing", g.index[g.flowing.to_numpy()]))
            out.append(_Segment(well, "shut_in", g.index[~g.flowing.to_numpy()]))
        elif q in ("WGOR", "WWCT"):
            f = g[g.flowing]
            v = f.observed.to_numpy(float)
            if q == "WGOR":
                bt = breakthrough_index(v, GAS_BREAKTHROUGH_RATIO * initial_gor(v))
            else:
                bt = breakthrough_index(v, WATER_BREAKTHROUGH_SEEN)
            bt = len(v) if bt is None else bt
            out.append(_Segment(well, "before", f.index[:bt]))
            out.append(_Segment(well, "after", f.index[bt:]))
        else:
            out.append(_Segment(well, "all", g.index))
    return out


def _run_ids(df: pd.DataFrame, context: pd.DataFrame) -> np.ndarray:
    """A run number per row: it changes where the well's signal may jump, i.e. where the well
    shuts in or reopens, or its observed oil rate changes by more than :data:`RATE_STEP`
    (read from ``context``, the whole observed table, controlled rates included)."""
    value = "value" if "value" in context else "observed"
    flowing = context.flowing.astype(bool) if "flowing" in context else \
        pd.Series(True, index=context.index)
    ctx = context.assign(_flowing=flowing)
    runs = np.zeros(len(df), int)
    for well, g in ctx.groupby("well", sort=False):
        open_at = g.groupby("days")._flowing.all()
        rate = g[g.quantity == "WOPR"].groupby("days")[value].mean()
        days = open_at.index.to_numpy(float)
        state = np.zeros(days.size, int)
        prev_open, prev_rate, k = None, float("nan"), 0
        for i, d in enumerate(days):
            now, r = bool(open_at.iloc[i]), float(rate.get(d, float("nan")))
            if prev_open is not None and (now != prev_open or (
                    math.isfinite(r) and math.isfinite(prev_rate)
                    and abs(r - prev_rate) > RATE_STEP * max(abs(prev_rate), 1e-9))):
                k += 1
            prev_open = now
            prev_rate = r if math.isfinite(r) else prev_rate
            state[i] = k
        rows = np.flatnonzero((df.well == well).to_numpy())
        at = np.searchsorted(days, df.days.to_numpy(float)[rows], side="right") - 1
        runs[rows] = np.where(at >= 0, state[np.clip(at, 0, None)], 0)
    return runs


def _series(df: pd.DataFrame, seg: _Segment, resid: np.ndarray | None, rel: bool,
            standardize: bool, runs: np.ndarray, position: np.ndarray) -> NoiseSeries:
    """The fitted rows of a segment as a series for :func:`fit_noise`: the observed values,
    or the residuals when ``resid`` is given; on the log scale for a relative noise; divided
    by sigma when ``standardize`` (every row's sigma known: only the correlation is wanted).
    The observed values' runs end where the signal may jump; residuals are one run (the
    simulator has taken the steps and transients out), so short runs between shut-ins still
    give the contrasts that tell the correlation."""
    idx = seg.idx[(df.loc[seg.idx, "period"] == "fit").to_numpy()]
    pos = np.asarray(idx, int)
    obs = df.loc[idx, "observed"].to_numpy(float)
    if standardize:
        v = (obs if resid is None else resid[pos]) / df.loc[idx, "sigma"].to_numpy(float)
    elif resid is None:
        v = np.log(np.where(obs > 0, obs, np.nan)) if rel else obs
    elif rel:
        sim = obs + resid[pos]
        v = np.log(np.where(sim > 0, sim, np.nan)) - np.log(np.where(obs > 0, obs, np.nan))
    else:
        v = resid[pos]
    run = runs[pos] if resid is None else np.zeros(pos.size, int)
    return NoiseSeries(v, df.loc[idx, "days"].to_numpy(float), position[pos], run)


def _level(df: pd.DataFrame, seg: _Segment) -> np.ndarray:
    """The signal's level at each row of a segment, fitted and held-back rows on their own."""
    return smoothed_level(df.loc[seg.idx, "observed"].to_numpy(float),
                          (df.loc[seg.idx, "period"] == "fit").to_numpy())


def _scale_data(df: pd.DataFrame, seg: _Segment, resid: np.ndarray | None, runs: np.ndarray,
                position: np.ndarray) -> ScaleData:
    """A segment's fitted rows on the value and on the logarithm, with the signal's level, for
    the choice of the noise's scale."""
    fitted = (df.loc[seg.idx, "period"] == "fit").to_numpy()
    return ScaleData(_series(df, seg, resid, False, False, runs, position),
                     _series(df, seg, resid, True, False, runs, position),
                     _level(df, seg)[fitted],
                     df.loc[seg.idx[fitted], "observed"].to_numpy(float))


# ============================================================================ filling sigma
@dataclass(frozen=True)
class Filled:
    """What :func:`fill_sigma` found besides the sigma it wrote into the rows."""

    rho: dict[str, float]
    rho_well: dict[str, dict[str, float]]
    report: dict
    segment: list[str]


@dataclass
class _Plan:
    """One quantity on its way to its levels: its segments, series and report entry."""

    q: str
    segs: list[_Segment]
    series: list[NoiseSeries]
    censored: list[bool]
    known: bool
    rho: float | None
    entry: dict
    scale: NoiseScale
    data: list[ScaleData] | None = None
    """The segments on the value and the logarithm, when the scale is chosen from the data."""


def fill_sigma(df: pd.DataFrame, resid: np.ndarray | None = None,
                statement: NoiseSection | None = None, context: pd.DataFrame | None = None
                ) -> Filled:
    """Fill missing sigma: first from the ``[noise]`` statements, then by estimation; return
    rho per quantity (and per well where stated), a report and each row's segment.

    ``resid`` (simulated - observed per row, optional): estimate from the residual series
    instead of the observed ones. Only rows of the fitted period are used (the held-back
    data must not set their own noise level). One correlation ``rho`` is estimated jointly
    over every quantity whose correlation is not stated (the data of one quantity alone rarely
    tell a correlation from a trend); where the data give every row's sigma, rho comes from
    the variogram of the standardized series (:func:`hmcore.scoring.noise.variogram_rho`).
    A segment too short to estimate takes the level pooled over its kind in the other wells;
    an after-breakthrough segment that none can estimate takes
    :data:`AFTER_BREAKTHROUGH_DEFAULT` (and, on the quantity's default scale, never less
    than the well's own level before
    breakthrough); a shut-in BHP segment with no estimate the flowing level.
    """
    context = df if context is None else context
    runs = _run_ids(df, context)
    inflow = (~df.derived & (df.flowing | ~df.quantity.isin(["WGOR", "WWCT"]))).to_numpy()
    position = np.full(len(df), -1.0)
    position[inflow] = df[inflow].groupby("series").cumcount().to_numpy(float)
    rho: dict[str, float] = {}
    rho_well: dict[str, dict[str, float]] = {}
    report: dict = {}
    label = [""] * len(df)
    source_of = "residuals" if resid is not None else "observed series"
    plans: list[_Plan] = []
    for q in ("WBHP", "WGOR", "WWCT", "WOPR", "WWPR", "WGPR"):
        segs = _segments(df, q)
        if not segs:
            continue
        for s in segs:
            for i in s.idx:
                label[i] = s.kind
        stated = (statement or {}).get(q)
        if stated is not None:
            _apply_statement(df, q, stated)
        own = (df.quantity == q) & ~df.derived
        known = bool(df.loc[own, "sigma"].notna().all())
        given = bool((df.loc[own, "sigma_source"] == "given").all())
        q_rho, w_rho = _stated_rho(df, q, stated, inflow)
        if w_rho:
            rho_well[q] = w_rho
        entry: dict = {"sigma_given": given,
                       "sigma_stated": bool((df.loc[own, "sigma_source"] == "stated").any()),
                       "estimated_from": source_of,
                       "rho_source": "stated" if q_rho is not None else "estimated"}
        if q == "WOPR" and not known:
            miss = own & df.sigma.isna()
            v = df.loc[miss, "observed"].abs()
            df.loc[miss, "sigma"] = np.maximum(OIL_RATE_SIGMA_REL * v, OIL_RATE_SIGMA_MIN)
            df.loc[miss, "sigma_source"] = "rate"
            rho[q] = 0.0 if q_rho is None else q_rho
            report[q] = {**entry, "sigma": f"{OIL_RATE_SIGMA_REL:.0%} of the rate (rate "
                         "control)", "rho": rho[q],
                         "rho_source": "stated" if q_rho is not None else "rate control"}
            continue
        if given and q_rho is None:  # the data's own sigma: rho as it always was
            rho[q] = variogram_rho([_standardized(df, s, resid) for s in segs])
            report[q] = {**entry, "rho": rho[q], "rho_source": "variogram"}
            continue
        rel = q in RELATIVE
        series = [_series(df, s, resid, rel, known, runs, position) for s in segs]
        censored = [q == "WWCT" and not known and _censored(df, s) for s in segs]
        data = [_scale_data(df, s, resid, runs, position) for s in segs] \
            if q in SCALED and not known else None
        plans.append(_Plan(q, segs, series, censored, known, q_rho, entry,
                           RELATIVE_NOISE if rel else ABSOLUTE_NOISE, data))
    joint = [(p, k) for p in plans if p.rho is None for k in range(len(p.segs))
             if not p.censored[k] and p.segs[k].kind in QUIET and p.q != "WWCT"]
    if not joint:
        joint = [(p, k) for p in plans if p.rho is None for k in range(len(p.segs))
                 if not p.censored[k]]
    shared = fit_noise([p.series[k] for p, k in joint],
                       groups=[(p.q, p.segs[k].kind) for p, k in joint]) if joint else None
    for p in plans:
        r = p.rho if p.rho is not None else min(max(shared.rho if shared else 0.0, 0.0),
                                                MAX_RHO)
        if p.data is not None:
            keep = [k for k in range(len(p.segs)) if not p.censored[k]]
            p.scale, p.entry["scale_scores"] = choose_scale([p.data[k] for k in keep], r,
                                                            p.scale)
            p.series = [s if c else d.series(p.scale)
                        for s, d, c in zip(p.series, p.data, p.censored)]
        p.entry |= p.scale.describe(1.0)
        p.entry.pop("relative_min", None)
        fit = _fit_at(p, r)
        rho[p.q] = r
        p.entry["rho"] = r
        if p.rho is None and shared is not None:
            p.entry["rho_range"] = list(shared.rho_range or (r, r))
            p.entry["rho_identified"] = shared.rho_identified
        if not p.known:
            p.entry["levels"], p.entry["uninformative"] = _fill_levels(
                df, p.q, p.segs, fit, p.scale, inflow)
            ends = [_fit_at(p, x) for x in shared.rho_range] if (
                p.rho is None and shared is not None and not shared.rho_identified) else []
            for lv in p.entry["levels"]:
                _level_range(lv, fit, ends)
        report[p.q] = p.entry
    return Filled(rho, rho_well, report, label)


def _level_range(level: dict, fit: NoiseFit, ends: list[NoiseFit]) -> None:
    """Add a level's range (``sigma_range``): the 95 % interval of a level from its number of
    contrasts, widened to the levels the ends of the supported correlations give when the
    data do not tell the correlation; ``uncertain`` when the range reaches beyond a factor
    :data:`UNCERTAIN_FACTOR` of the level, or when the level was not estimated (a default)."""
    k, kind = level.pop("_k"), level.pop("_kind")
    sig = level["sigma"]
    if level["source"] == "default" or level["contrasts"] <= 0 or not sig > 0:
        level["uncertain"] = level["source"] == "default"
        return
    scales = [1.0]
    for end in ends:
        if level["method"] == "contrasts":
            scales.append(end.sigma[k] / fit.sigma[k])
        elif level["source"] == "pooled":
            scales.append(end.pooled(kind) / fit.pooled(kind))
    scales = [x for x in scales if math.isfinite(x) and x > 0]
    low, high = level_interval(level["contrasts"])
    level["sigma_range"] = [sig * min(scales) * low, sig * max(scales) * high]
    level["uncertain"] = bool(level["sigma_range"][1] > UNCERTAIN_FACTOR * sig
                              or level["sigma_range"][0] < sig / UNCERTAIN_FACTOR)


def _fit_at(p: _Plan, rho: float) -> NoiseFit:
    """The levels of a quantity's segments at correlation ``rho`` (NaN for censored ones)."""
    keep = [k for k in range(len(p.segs)) if not p.censored[k]]
    fit = fit_noise([p.series[k] for k in keep], rho=rho)
    sigma = [float("nan")] * len(p.segs)
    contrasts = [np.zeros(0)] * len(p.segs)
    for k, sg, u in zip(keep, fit.sigma, fit.contrasts):
        sigma[k], contrasts[k] = sg, u
    return NoiseFit(tuple(sigma), rho, tuple(contrasts))


def _standardized(df: pd.DataFrame, seg: _Segment, resid: np.ndarray | None) -> np.ndarray:
    """A segment's fitted rows divided by their own sigma (the residuals, when given)."""
    idx = seg.idx[(df.loc[seg.idx, "period"] == "fit").to_numpy()]
    sig = df.loc[idx, "sigma"].to_numpy(float)
    if resid is None:
        return df.loc[idx, "observed"].to_numpy(float) / sig
    r = resid[np.asarray(idx, int)]
    return (r / sig)[np.isfinite(r)]


def _censored(df: pd.DataFrame, seg: _Segment) -> bool:
    """Whether a water-cut segment reads as noise clipped at 0 (:data:`CENSORED_SHARE` of its
    fitted values exactly 0)."""
    fitted = df.loc[seg.idx][(df.loc[seg.idx, "period"] == "fit").to_numpy()]
    obs = fitted.observed.to_numpy(float)
    return bool(obs.size) and float(np.mean(obs <= 0)) >= CENSORED_SHARE


def _apply_statement(df: pd.DataFrame, q: str, stated: QuantityNoise) -> None:
    """Rows of ``q`` without a sigma of their own take the stated level (source 'stated');
    a relative level that comes out 0 (a zero value) is left to the estimate."""
    rows = df[(df.quantity == q) & ~df.derived & df.sigma.isna()]
    for well, g in rows.groupby("well", sort=False):
        sigma = stated.for_well(str(well)).sigma(g.observed.to_numpy(float))
        if sigma is None:
            continue
        ok = np.isfinite(sigma) & (sigma > 0)
        df.loc[g.index[ok], "sigma"] = sigma[ok]
        df.loc[g.index[ok], "sigma_source"] = "stated"


def _stated_rho(df: pd.DataFrame, q: str, stated: QuantityNoise | None, inflow: np.ndarray
                ) -> tuple[float | None, dict[str, float]]:
    """The stated AR(1) correlation of ``q`` (None: not stated) and the wells' own: a
    correlation length turned into rho by the median spacing of the rows it correlates."""
    if stated is None:
        return None, {}
    rows = df[inflow & (df.quantity == q).to_numpy()]
    spacing = {str(w): float(np.median(np.diff(g.days.to_numpy(float)))) if len(g) > 1
               else float("nan") for w, g in rows.groupby("well", sort=False)}
    finite = [s for s in spacing.values() if math.isfinite(s)]
    q_rho = stated.rho(float(np.median(finite)) if finite else float("nan"))
    own = {w: r for w in stated.wells if w in spacing
           and (r := stated.for_well(w).rho(spacing[w])) is not None and r != q_rho}
    return q_rho, own


def _fill_levels(df: pd.DataFrame, q: str, segs: list[_Segment], fit: NoiseFit,
                 scale: NoiseScale, inflow: np.ndarray) -> tuple[list[dict], list[str]]:
    """Set the estimated sigma of every row of ``segs`` that has none (``scale`` turns a level
    into each row's sigma; a water cut clipped at 0 and the water cut's default after
    breakthrough are absolute, GOR's default relative); the levels and the wells whose series
    are uninformative (see :func:`_floor`)."""
    kinds: dict[str, list[int]] = {}
    for i, s in enumerate(segs):
        kinds.setdefault(s.kind, []).append(i)
    levels, flagged = [], set()
    own_before: dict[str, float] = {}
    for i, s in enumerate(segs):
        if not len(s.idx):
            continue
        miss = df.loc[s.idx, "sigma"].isna().to_numpy()
        if not miss.any():
            continue
        fitted = df.loc[s.idx][(df.loc[s.idx, "period"] == "fit").to_numpy()]
        sig, source, method = _shrunk(fit, i, kinds[s.kind]), "estimated", "contrasts"
        pool = sum(fit.contrasts[j].size for j in kinds[s.kind])
        own = fit.contrasts[i].size
        count = own + min(SHRINK_CONTRASTS, pool - own)
        obs = fitted.observed.to_numpy(float)
        if q == "WWCT" and _censored(df, s):
            sig, method, count = censored_sigma(obs), "censored", obs.size
        if not math.isfinite(sig):
            sig, source, method = _fallback(q, s.kind, fit, kinds)
            count = pool if source == "pooled" else 0
        row_scale = scale
        if method == "censored" or (method == "default after breakthrough" and q == "WWCT"):
            row_scale = ABSOLUTE_NOISE
        elif method == "default after breakthrough":
            row_scale = RELATIVE_NOISE
        rel = row_scale.mode != "absolute"
        if s.kind == "before" and row_scale == scale:
            own_before[s.well] = sig
        elif s.kind == "after" and row_scale == scale == (
                RELATIVE_NOISE if q in RELATIVE else ABSOLUTE_NOISE) and \
                sig < own_before.get(s.well, 0.0):  # on the default scale only
            sig = own_before[s.well]
        floor, uninformative = _floor(df, q, s.well, rel, inflow, obs)
        if uninformative:
            flagged.add(s.well)
        if sig < floor:
            sig, source = floor, "floor"
        if rel:  # a row whose level is 0 takes the segment's least positive level
            level = _level(df, s)
            positive = level[np.isfinite(level) & (level > 0)]
            least = float(positive.min()) if positive.size else 0.0
            sigma = np.maximum(row_scale.row_sigma(sig, np.fmax(level, least)), 1e-12)
        else:
            sigma = np.full(len(s.idx), sig)
        df.loc[s.idx[miss], "sigma"] = sigma[miss]
        df.loc[s.idx[miss], "sigma_source"] = source
        levels.append({"well": s.well, "segment": s.kind, "sigma": sig, "relative": rel,
                       **row_scale.describe(sig), "n": len(s.idx), "source": source,
                       "method": method, "contrasts": int(count),
                       "uninformative": uninformative, "_k": i, "_kind": kinds[s.kind]})
    return levels, sorted(flagged)


def _shrunk(fit: NoiseFit, i: int, kind: list[int]) -> float:
    """Series ``i``'s level leaning on its kind's level pooled over all wells: a geometric
    mean weighted by the series' contrasts and :data:`SHRINK_CONTRASTS` for the pool (NaN
    when the series has too few contrasts of its own)."""
    own, pool = fit.sigma[i], fit.pooled(kind)
    if not (math.isfinite(own) and math.isfinite(pool)) or own <= 0 or pool <= 0:
        return own
    n = fit.contrasts[i].size
    return math.exp((n * math.log(own) + SHRINK_CONTRASTS * math.log(pool))
                    / (n + SHRINK_CONTRASTS))


def _fallback(q: str, kind: str, fit: NoiseFit, kinds: dict[str, list[int]]
              ) -> tuple[float, str, str]:
    """Level, source and method of a segment too short to estimate on its own."""
    s = fit.pooled(kinds.get(kind, []))
    if math.isfinite(s):
        return s, "pooled", f"pooled over the {kind} segments"
    if kind == "after" and q in AFTER_BREAKTHROUGH_DEFAULT:
        return AFTER_BREAKTHROUGH_DEFAULT[q], "default", "default after breakthrough"
    s = fit.pooled(kinds.get("flowing", [])) if kind == "shut_in" else float("nan")
    if math.isfinite(s):
        return s, "default", "the flowing level (no shut-in run to estimate from)"
    s = fit.pooled([i for v in kinds.values() for i in v])
    if math.isfinite(s):
        return s, "default", "pooled over all segments"
    return 0.0, "floor", "no contrast"


def _floor(df: pd.DataFrame, q: str, well: str, rel: bool, inflow: np.ndarray,
           segment: np.ndarray) -> tuple[float, bool]:
    """The least sigma an estimate of ``q`` at ``well`` may give in a segment whose fitted
    values are ``segment``, and whether the well's series is uninformative: its whole fitted
    series lies within the quantity's floor of zero (a water cut of 3e-5 against 0.01).

    A floor never sits above the signal it would hide: an absolute floor is at most
    :data:`FLOOR_SIGNAL_SHARE` of the segment's typical (median) value, or of its largest when
    the median is 0 (a water cut of 1e-5 before breakthrough in a well whose water cut later
    rises keeps its own noise); the level of an all-zero series stays at the floor."""
    mask = inflow & (df.quantity == q).to_numpy() & (df.well == well).to_numpy() & \
        (df.period == "fit").to_numpy()
    values = np.abs(df.observed.to_numpy(float)[mask])
    values = values[np.isfinite(values)]
    top = float(values.max()) if values.size else 0.0
    within = q in SIGMA_FLOOR and bool(values.size) and top <= SIGMA_FLOOR[q]
    if rel:  # a relative level: the gauge's relative resolution
        floor = SIGMA_FLOOR["WGOR_REL"] if q == "WGOR" else SIGMA_FLOOR["RATE_REL"]
        return floor, within or bool(values.size and top <= 0)
    seg = np.abs(segment[np.isfinite(segment)])
    typical = float(np.median(seg)) if seg.size else 0.0
    if typical <= 0:
        typical = float(seg.max()) if seg.size else 0.0
    floor = SIGMA_FLOOR.get(q, math.inf)  # GOR or a rate read as absolute: its share only
    if typical > 0:
        floor = min(floor, FLOOR_SIGNAL_SHARE * typical)
    return (floor if math.isfinite(floor) else 0.0), within
