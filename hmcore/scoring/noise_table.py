"""The noise a fit assumes, as a table for people: per quantity, noise segment and well, where
each level comes from (``given`` in the data, ``stated`` in the case's ``[noise]`` section,
``estimated`` from the data, ``pooled`` over the other wells, ``default``, ``floor``, ``rate``),
the level, the time correlation and whether the series is uninformative.

For ``hmflow check``, ``hmflow init`` and the report: :func:`case_noise_text` (a loaded case)
or :func:`format_noise_table` (an ObservationSet) give the text; :func:`noise_table` is the same
as data (one row per well), :func:`noise_summary` its rows gathered over wells that share
source, flag and correlation.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from hmcore.scoring.noise import SIGMA_FLOOR
from hmcore.scoring.noise_fill import RELATIVE
from hmcore.scoring.observations import ObservationSet

TABLE_COLUMNS = ["quantity", "segment", "well", "source", "sigma", "relative", "rho",
                 "uninformative", "uncertain", "low", "high", "n"]


def noise_table(obs: ObservationSet) -> pd.DataFrame:
    """One row per quantity, noise segment and well of the rows the fit weighs (measured rows in
    the whitened vector, fitted and held back): the main source of their sigma, its median
    (``sigma``, in the quantity's units) and, for GOR and rates or a relative statement, its
    median share of the value (``relative``); the AR(1) correlation ``rho`` and the
    uninformative flag (:attr:`ObservationSet.uninformative`)."""
    rows = obs.rows.assign(segment=list(obs.segment) if obs.segment else "all")
    idx = np.flatnonzero(rows.in_vector.to_numpy() & ~rows.derived.to_numpy())
    rows = rows.iloc[idx].assign(rho=obs.row_rho(idx))
    flags = obs.uninformative
    levels = {(q, lv["well"], lv["segment"]): lv for q, entry in obs.noise_report.items()
              for lv in entry.get("levels", [])}
    out = []
    for (q, seg, well), g in rows.groupby(["quantity", "segment", "well"], sort=False):
        source = g.sigma_source.value_counts().index[0]
        share = (g.sigma / g.observed.abs().where(g.observed != 0)).median()
        level = levels.get((q, well, seg), {})
        relative = q in RELATIVE or source == "rate" or (
            source == "stated" and _stated_mode(obs, q, str(well)) in ("REL", "RELMIN"))
        if source == level.get("source") and "relative" in level:
            relative = bool(level["relative"])  # the scale the data chose (noise_scale)
        low, high = level.get("sigma_range", (float("nan"), float("nan")))
        out.append({"quantity": q, "segment": seg, "well": well, "source": source,
                    "sigma": float(g.sigma.median()),
                    "relative": float(share) if relative else float("nan"),
                    "rho": float(g.rho.iloc[0]), "uninformative": (q, well) in flags,
                    "uncertain": bool(level.get("uncertain", False)) and source == level.get(
                        "source"), "low": float(low), "high": float(high), "n": len(g)})
    return pd.DataFrame(out, columns=TABLE_COLUMNS)


def _stated_mode(obs: ObservationSet, q: str, well: str) -> str | None:
    """ERT's error mode of the statement for ``q`` at ``well`` (None: nothing stated)."""
    stated = (obs.statement or {}).get(q)
    return stated.for_well(well).mode if stated is not None else None


def noise_summary(obs: ObservationSet) -> pd.DataFrame:
    """:func:`noise_table` gathered over the wells that share a quantity, segment, source,
    flag and correlation (and, for stated levels, the level): ``wells`` ('all' or their
    names), the median level and its range over the wells."""
    table = noise_table(obs)
    table = table.assign(_rho=table.rho.round(3), _stated=np.where(
        table.source == "stated", table.relative.fillna(table.sigma).round(12), np.nan))
    out = []
    for (q, seg), part in table.groupby(["quantity", "segment"], sort=False):
        every = set(part.well)
        keys = ["source", "uninformative", "_rho", "_stated"]
        for (source, flag, _, _), g in part.groupby(keys, sort=False, dropna=False):
            wells = "all" if set(g.well) == every and len(g) > 1 else ", ".join(map(str, g.well))
            rel = g.relative.notna().all()
            level = g.relative if rel else g.sigma
            out.append({"quantity": q, "segment": seg, "wells": wells,
                        "n_wells": len(g), "source": source, "relative": bool(rel),
                        "sigma": float(level.median()), "sigma_min": float(level.min()),
                        "sigma_max": float(level.max()), "rho": float(g.rho.median()),
                        "uninformative": bool(flag), "uncertain": bool(g.uncertain.any()),
                        "low": float(g.low.min()), "high": float(g.high.max()),
                        "n": int(g.n.sum())})
    return pd.DataFrame(out)


def flagged_series(summary: pd.DataFrame | None, rows: pd.DataFrame) -> set[tuple[str, str]]:
    """The (quantity, well) pairs a :func:`noise_summary` flags uninformative (its ``wells``:
    'all', the wells of ``rows`` that have the quantity, or their names), as
    :attr:`ObservationSet.uninformative` gave them."""
    if summary is None or summary.empty or "uninformative" not in summary:
        return set()
    out = set()
    for r in summary[summary.uninformative.astype(bool)].itertuples():
        wells = (set(rows.well[rows.quantity == r.quantity]) if r.wells == "all"
                 else {w.strip() for w in str(r.wells).split(",")})
        out |= {(r.quantity, str(w)) for w in wells}
    return out


def format_noise_table(obs: ObservationSet) -> str:
    """The noise the fit will assume, in plain text (one line per :func:`noise_summary` row,
    then what the flags mean)."""
    summary = noise_summary(obs)
    if summary.empty:
        return "noise: no row to weigh"
    lines = [("noise the fit assumes (sigma per row, its source; rho: the AR(1) correlation "
              "of consecutive rows)")]
    for r in summary.itertuples():
        wells = f"all {r.n_wells} wells" if r.wells == "all" else r.wells
        level = _level(r.sigma, r.relative)
        if r.sigma_max > r.sigma_min * 1.05:
            level += f" ({_level(r.sigma_min, r.relative)} to {_level(r.sigma_max, r.relative)})"
        flag = "  UNINFORMATIVE" if r.uninformative else ""
        if r.uncertain:
            flag += ("  uncertain" if not math.isfinite(r.low) else
                     f"  uncertain: {_level(r.low, r.relative)} to {_level(r.high, r.relative)}")
        lines.append(f"  {r.quantity:<5} {r.segment:<8} {r.source:<9} {level:<28} "
                     f"rho {r.rho:.2f}  {wells}{flag}")
    lines += _notes(obs, summary)
    return "\n".join(lines)


def noise_markdown(summary: pd.DataFrame) -> str:
    """A :func:`noise_summary` table (as stored with a campaign's case) as a Markdown section
    for the report: which noise the fit assumed and where each level comes from."""
    if summary.empty:
        return ""
    lines = ["## The noise the fit assumed", "",
             ("Sigma per row and its source: `given` in the data, `stated` in the case's "
              "`[noise]` section, `estimated` from the series, `pooled` over other wells, "
              "`default`, `floor` or `rate`; rho is the AR(1) correlation of consecutive "
              "rows."),
             "", "| quantity | segment | wells | source | sigma | rho | flag |",
             "|---|---|---|---|---|---|---|"]
    for r in summary.itertuples():
        level = _level(r.sigma, r.relative)
        if r.sigma_max > r.sigma_min * 1.05:
            level += f" ({_level(r.sigma_min, r.relative)} to {_level(r.sigma_max, r.relative)})"
        flag = ", ".join(f for f, on in (("uninformative", r.uninformative),
                                         ("uncertain", r.uncertain)) if on)
        wells = f"all {r.n_wells}" if r.wells == "all" else r.wells
        lines.append(f"| {r.quantity} | {r.segment} | {wells} | {r.source} | {level} | "
                     f"{r.rho:.2f} | {flag} |")
    if summary.uninformative.any():
        lines += ["", ("An uninformative series lies within the noise floor of zero over the "
                       "whole fitted history: the fit can hardly learn from it; state its error "
                       "in `[noise]` to weigh it otherwise.")]
    return "\n".join(lines) + "\n"


def _level(value: float, relative: bool) -> str:
    if not math.isfinite(value):
        return "-"
    return f"{100 * value:.3g} %" if relative else f"{value:.3g}"


def _notes(obs: ObservationSet, summary: pd.DataFrame) -> list[str]:
    notes = []
    for q, entry in obs.noise_report.items():
        if entry.get("rho_identified") is False:
            lo, hi = entry.get("rho_range", [0.0, 0.0])
            notes.append(f"  {q}: the data do not tell the correlation (rho {lo:.2f}-{hi:.2f} "
                         "fit as well): the levels assume the middle; state correlation_days "
                         "in [noise] if it is known")
    if summary.uninformative.any():
        floors = ", ".join(f"{q} {v:g}" for q, v in SIGMA_FLOOR.items() if "_" not in q)
        notes.append("  UNINFORMATIVE: the whole fitted series is within the noise floor of "
                     f"zero ({floors}); its sigma comes from the data, not the floor, so the "
                     "fit still sees it; state its error in [noise] to weigh it otherwise")
    if summary.uncertain.any():
        notes.append("  uncertain: the level's 95 % range (from its number of contrasts and the "
                     "correlations the data support) reaches beyond a factor 1.5 of it; the "
                     "fit's residuals refine it (ObservationSet.refine), or state it in [noise]")
    if (summary.source == "default").any():
        notes.append("  default: a level the data of that segment could not give (too few "
                     "rows between shut-ins): the default after breakthrough, or the flowing "
                     "level for shut-in BHP")
    return notes


def case_noise_text(case) -> str:
    """The noise table of a loaded case (:func:`hmcore.cases.load_case`), as ``hmflow check``
    and ``hmflow init`` print it: the data's sigma, the ``[noise]`` statements and the
    estimates of :meth:`ObservationSet.from_case`."""
    return format_noise_table(ObservationSet.from_case(case))
