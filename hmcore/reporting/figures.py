"""The report's figures as PNG bytes (matplotlib, object API: no pyplot state, thread-safe).

Each function takes stored tables (no simulator, no file reading) and returns one PNG:
per-well curves (observed with its noise band, prior centre, deck or truth, best case; the
held-back period shaded), best-so-far E against calls, the well x response C_match heatmap,
parameter traces and the best values against their bounds, failed and penalised calls by kind,
and the forecast fan. Units come from the summary file (the deck's own unit system).
"""

from __future__ import annotations

import io
import math

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.layout_engine import ConstrainedLayoutEngine

from hmcore.scoring.information import NoInformation

# response quantity -> (title, observed response category in ObservationSet rows)
PANELS = (("WOPR", "oil rate"), ("WWPR", "water rate"), ("WGPR", "gas rate"),
          ("WBHP", "bottom-hole pressure"), ("WGOR", "gas-oil ratio"), ("WWCT", "water cut"))
INJECTOR_PANELS = (("WWIR", "water injection rate"), ("WGIR", "gas injection rate"),
                   ("WBHP", "bottom-hole pressure"))
STYLE = {"best": {"color": "#1f5fbf", "lw": 1.8, "label": "best case", "zorder": 2.5},
         "centre": {"color": "#888888", "lw": 1.2, "ls": "--", "label": "prior centre"},
         "truth": {"color": "#111111", "lw": 1.3, "ls": (0, (4, 2.5)), "label": "truth",
                   "zorder": 3},
         "deck": {"color": "#111111", "lw": 1.3, "ls": ":", "label": "deck's own values",
                  "zorder": 3}}
"""Line styles; the truth (or the deck's own values) dashed black above the best case, which a
good match hides it under otherwise: the best case shows through its gaps."""
DPI = 90


def png(fig: Figure) -> bytes:
    """``fig`` as PNG bytes; zlib level 1: the same pixels as the default level 6, encoded
    about twice as fast, in files about a fifth larger. A figure in a constrained layout
    already fits its canvas, so it is drawn once, without the extra draw of
    ``bbox_inches="tight"`` (a quarter of a well figure's time)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches=None if _constrained(fig) else "tight",
                pil_kwargs={"compress_level": 1})
    return buf.getvalue()


def unit_of(curves: pd.DataFrame, quantity: str) -> str:
    u = curves.loc[curves.quantity == quantity, "unit"]
    u = u[u.astype(str).str.len() > 0] if len(u) else u
    if quantity == "WWCT":
        return "fraction"
    return str(u.iloc[0]).lower() if len(u) else ""


def well_curves(well: str, observed: pd.DataFrame, curves: pd.DataFrame,
                history_end: float | None) -> bytes:
    """Six panels for one well (an injector's: its injection rates and BHP). ``observed``:
    ObservationSet rows of this well (``quantity, days, observed, sigma, period``);
    ``curves``: the curves artifact rows of this well."""
    end = float(curves.days.max()) if len(curves) else None
    panels = panels_of(observed, curves)
    rows = 2 if len(panels) > 3 else 1
    fig = Figure(figsize=(11.5, 6.2 if rows == 2 else 3.5), layout="constrained")
    axes = fig.subplots(rows, 3, sharex=True, squeeze=False)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    for ax, (q, title) in zip(axes.flat, panels):
        obs = observed[observed.quantity == q].sort_values("days")
        shade_periods(ax, observed, history_end, end)
        observed_points(ax, q, obs)
        for member in ("centre", "best", "deck", "truth"):  # the truth last, on top
            sel = curves[(curves.member == member) & (curves.quantity == q)].sort_values("days")
            if len(sel):
                ax.plot(sel.days, sel.value, **STYLE[member])
        ax.set_title(f"{well}: {title}", fontsize=10)
        ax.set_ylabel(unit_of(curves, q))
        response_axis(ax, q)
    for ax in axes[-1]:
        ax.set_xlabel("days since start")
    shared_legend(fig, axes, rows)
    return png(fig)


def shade_periods(ax, observed: pd.DataFrame, history_end: float | None,
                  end: float | None) -> None:
    """Shade the held-back period (measured, not fitted: from ``history_end`` to the last
    observation) and the forecast (no data: from there to ``end``, the schedule's end)."""
    if history_end is None or end is None:
        return
    last_obs = float(observed.days.max()) if len(observed) else history_end
    if last_obs > history_end:
        ax.axvspan(history_end, min(last_obs, end), color="#f3e9d2", zorder=0,
                   label="held back (not fitted)")
    if end > max(last_obs, history_end):
        ax.axvspan(max(last_obs, history_end), end, color="#e8eef7", zorder=0,
                   label="forecast (no data)")


def observed_points(ax, quantity: str, obs: pd.DataFrame) -> None:
    """The observed points of one response (``obs``: rows with days, observed, sigma) and
    their noise band, +/- 1 sigma."""
    if len(obs):
        lo, hi = noise_band(quantity, obs.observed.to_numpy(float), obs.sigma.to_numpy(float))
        ax.fill_between(obs.days, lo, hi, color="#d62728", alpha=0.15, lw=0,
                        label="observed \u00b1 1 sigma")
        ax.plot(obs.days, obs.observed, "o", ms=3, color="#d62728", label="observed",
                zorder=2.7)  # above the best case, below the truth's dashes


def response_axis(ax, quantity: str) -> None:
    """A response panel's y range, from 0 to what the panel draws (a water cut of a few
    percent on an axis of a few percent, never above 1), a little below 0 so that points at
    0 show; and its grid."""
    ax.autoscale_view()
    top = ax.get_ylim()[1]
    if quantity == "WWCT":
        top = min(top, 1.02)
    top = top if top > 0 else 1.0
    ax.set_ylim(-0.02 * top, top)
    ax.grid(alpha=0.3)


def shared_legend(fig: Figure, axes: np.ndarray, rows: int, ncol: int | None = None) -> None:
    """One legend below the panels with every label any panel drew, once (``ncol`` columns;
    all in one row by default); in a constrained layout, outside the panels, which make room
    for it. ``rows`` (the panels' rows) no longer matters: the legend hangs below them."""
    handles, labels = axes.flat[0].get_legend_handles_labels()
    for ax in axes.flat[1:]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    if _constrained(fig):
        fig.legend(handles, labels, loc="outside lower center", ncol=ncol or len(labels),
                   frameon=False)
        return
    # otherwise hung from the figure's bottom edge, below the x labels (PNGs are cut to fit)
    fig.legend(handles, labels, loc="upper center", ncol=ncol or len(labels), frameon=False,
               bbox_to_anchor=(0.5, 0.0))


def _constrained(fig: Figure) -> bool:
    return isinstance(fig.get_layout_engine(), ConstrainedLayoutEngine)


def panels_of(observed: pd.DataFrame, curves: pd.DataFrame) -> tuple[tuple[str, str], ...]:
    """A producer's six panels, or an injector's: the phases it injects and its BHP."""
    def shows(q: str) -> bool:
        sel = curves[curves.quantity == q]
        return bool((observed.quantity == q).any() or (len(sel) and (sel.value > 0).any()))

    injected = tuple(p for p in INJECTOR_PANELS[:2] if shows(p[0]))
    return injected + INJECTOR_PANELS[2:] if injected else PANELS


def noise_band(quantity: str, y: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """y +/- sigma, never below 0 (rates, pressures, ratios) nor above 1 (water cut)."""
    s = np.where(np.isfinite(sigma), sigma, 0.0)
    lo, hi = np.maximum(y - s, 0.0), y + s
    if quantity == "WWCT":
        hi = np.minimum(hi, 1.0)
    return lo, hi


def best_so_far(table: pd.DataFrame, floor: float | None, centre: float | None,
                objective: str = "E", references: dict | None = None) -> bytes:
    """Every call's E (valid, penalised, failed marked apart) and the E of the best call so
    far. When another ``objective`` chose the best call (the likelihood, a column of
    ``table``), a panel above draws it the same way, the line it chose by; the E below then
    follows the call that objective holds best, which is not always the lowest E.
    ``floor``/``centre``: the reference runs' E; ``references``: their records (``floor``,
    ``centre`` -> ``E``, ``likelihood``)."""
    chooses = objective != "E" and objective in table
    fig = Figure(figsize=(8, 6.5 if chooses else 4))
    axes = fig.subplots(2, 1, sharex=True) if chooses else [fig.subplots()]
    calls = table["index"].to_numpy(int) + 1
    ok, bad, fails = (table.status == s for s in ("COMPLETE", "INVALID", "FAIL"))
    best = _best_positions(table[objective if chooses else "E"], ok)
    e_of_best = np.where(best >= 0, table.E.to_numpy(float)[np.maximum(best, 0)], np.nan)
    panels = [(axes[-1], "E", e_of_best, "misfit E (log scale)", floor, centre)]
    if chooses:
        refs = references or {}
        panels.insert(0, (axes[0], objective, table[objective].to_numpy(float)[
            np.maximum(best, 0)] * np.where(best >= 0, 1.0, np.nan),
            f"{objective} (log scale; chooses)",
            (refs.get("floor") or {}).get(objective), (refs.get("centre") or {}).get(objective)))
    for ax, column, line, ylabel, ref_floor, ref_centre in panels:
        values = table[column]
        ax.semilogy(calls[ok], values[ok], ".", color="#1f5fbf", alpha=0.5, label="valid call")
        if bad.any():
            ax.semilogy(calls[bad], values[bad].where(values[bad] > 0), "x", color="#e69f00",
                        alpha=0.6, label="penalised (never best)")
        label = ("best so far" if column == objective or not chooses
                 else f"E of the best call so far (by {objective})")
        ax.step(calls, line, where="post", color="#1f5fbf", lw=2, label=label)
        for value, name, style in ((ref_floor, f"truth / deck {column}", ":"),
                                   (ref_centre, f"prior-centre {column}", "--")):
            if value is not None and math.isfinite(value) and value > 0:
                ax.axhline(value, color="#444444", ls=style, lw=1, label=name)
        for c in calls[fails]:
            ax.axvline(c, color="#d62728", alpha=0.25, lw=1)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8, loc="best")
    axes[-1].set_xlabel("simulator call")
    axes[0].set_title("Best so far against simulator calls"
                      + (" (red lines: failed calls)" if fails.any() else ""), fontsize=10)
    return png(fig)


def _best_positions(values: pd.Series, valid: pd.Series) -> np.ndarray:
    """For each position, the position of the lowest valid value up to it (-1 before the
    first valid one)."""
    out, best, low = np.full(len(values), -1), -1, math.inf
    for k, (v, good) in enumerate(zip(values.to_numpy(float), valid.to_numpy(bool))):
        if good and math.isfinite(v) and v < low:
            best, low = k, v
        out[k] = best
    return out


def cmatch_heatmap(wells: pd.DataFrame, marks: dict[tuple[str, str], str] | None = None
                   ) -> bytes:
    """:func:`heatmap_figure` as PNG."""
    return png(heatmap_figure(wells, marks))


def heatmap_figure(wells: pd.DataFrame, marks: dict[tuple[str, str], str] | None = None
                   ) -> Figure:
    """``wells``: :func:`hmcore.scoring.metrics.well_table` (well x response C_match, %);
    ``marks``: (well, response) -> why it carries no information
    (:func:`hmcore.scoring.information.uninformative`): such a cell is grey, its C_match
    followed by the reason in short (:data:`SHORT_WHY`), never coloured as a match or a miss
    (the coloured image, the figure's second, masks it)."""
    marks = marks or {}
    # a response no well has (injection in a field without injectors) is no column of n/a
    cats = [c for c in wells.columns if c != "well" and wells[c].notna().any()] or [
        c for c in wells.columns if c != "well"]
    data = wells[cats].to_numpy(float)
    grey = np.array([[(w, c) in marks for c in cats] for w in wells.well], bool).reshape(
        data.shape)
    fig = Figure(figsize=(1.3 * len(cats) + 2, 0.45 * len(wells) + 1.6))
    ax = fig.subplots()
    ax.imshow(np.where(grey, 1.0, np.nan), cmap="Greys", vmin=0, vmax=6, aspect="auto")
    im = ax.imshow(np.ma.masked_where(grey | ~np.isfinite(data), data), cmap="RdYlGn",
                   vmin=50, vmax=100, aspect="auto")
    ax.set_xticks(range(len(cats)), cats)
    ax.set_yticks(range(len(wells)), wells.well)
    for i in range(data.shape[0]):
        for j in range(data.shape[1]):
            v = data[i, j]
            text = "n/a" if not math.isfinite(v) else f"{v:.1f}"
            why = marks.get((wells.well.iloc[i], cats[j]))
            if why:
                text += "\n" + SHORT_WHY.get(why, why)
            ax.text(j, i, text, ha="center", va="center", fontsize=8 if not why else 7,
                    color="#555555" if why else "black")
    fig.colorbar(im, ax=ax, label="C_match (%) = 100 / (1 + NMSE)")
    ax.set_title("Best case: C_match per well and response"
                 + ("\n(grey: carries no information, not scored)" if marks else ""),
                 fontsize=10)
    return fig


SHORT_WHY = {NoInformation.RATE_CONTROL.value: "rate control",
             NoInformation.NEAR_ZERO.value: "zero \u00b1 noise",
             NoInformation.NOISE_FLOOR.value: "at noise floor"}
"""A reason a response carries no information, short enough for a heatmap cell."""


def parameter_traces(table: pd.DataFrame, bounds: dict[str, tuple[float, float]],
                     best: dict[str, float] | None) -> bytes:
    """Each parameter's value at every call (valid, penalised, failed) within its bounds, and
    the best case's value."""
    names = list(bounds)
    fig = Figure(figsize=(8.5, 1.7 * len(names) + 0.9), layout="constrained")
    axes = np.atleast_1d(fig.subplots(len(names), 1, sharex=True))
    calls = table["index"].to_numpy(int) + 1
    colours = {"COMPLETE": "#1f5fbf", "INVALID": "#e69f00", "FAIL": "#d62728"}
    for ax, name in zip(axes, names):
        col = f"p_{name}"
        for status, colour in colours.items():
            sel = (table.status == status).to_numpy()
            if sel.any() and col in table:
                ax.plot(calls[sel], table[col][sel], ".", color=colour, ms=4,
                        label={"COMPLETE": "valid", "INVALID": "penalised",
                               "FAIL": "failed"}[status])
        lo, hi = bounds[name]
        ax.axhline(lo, color="#444444", lw=0.8)
        ax.axhline(hi, color="#444444", lw=0.8)
        if best and name in best:
            ax.axhline(best[name], color="#2e8b57", lw=1.5, ls="--", label="best")
        pad = 0.08 * (hi - lo) if hi > lo else 1.0
        ax.set_ylim(lo - pad, hi + pad)  # the bounds inside the panel, not on its frame
        ax.set_ylabel(name, fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("simulator call")
    axes[0].set_title("Parameter values proposed, call by call (lines: bounds)", fontsize=10)
    shared_legend(fig, axes, len(names))  # below the panels: over the first, it hid calls
    return png(fig)


def best_against_bounds(bounds: dict[str, tuple[float, float]], best: dict[str, float],
                        truth: dict[str, float] | None) -> bytes:
    """Where the best value sits in each parameter's range (0 = low bound, 1 = high): a row
    per parameter, its bounds at the ends, the best value over its marker (room kept above
    the first row, clear of the title), the legend below the axes (never over a bound)."""
    names = list(bounds)
    fig = Figure(figsize=(8, 0.5 * len(names) + 1.4), layout="constrained")
    ax = fig.subplots()
    for i, name in enumerate(names):
        lo, hi = bounds[name]
        ax.plot([0, 1], [i, i], color="#cccccc", lw=6, solid_capstyle="butt")
        x = (best[name] - lo) / (hi - lo)
        ax.plot(x, i, "o", color="#1f5fbf", ms=9, label="best" if i == 0 else None)
        ax.annotate(f"{best[name]:.4g}", (x, i), textcoords="offset points", xytext=(0, 8),
                    ha="center", fontsize=8)
        if truth and name in truth:
            ax.plot((truth[name] - lo) / (hi - lo), i, "D", color="#2e8b57", ms=7,
                    mfc="none", label="truth" if i == 0 else None)
        ax.text(-0.02, i, f"{lo:g}", ha="right", va="center", fontsize=8)
        ax.text(1.02, i, f"{hi:g}", ha="left", va="center", fontsize=8)
    ax.set_yticks(range(len(names)), names)
    ax.set_xlim(-0.12, 1.12)
    ax.set_xticks([])
    ax.set_ylim(len(names) - 0.5, -0.85)  # top to bottom; the first row's label under the title
    for side in ("top", "right", "bottom"):
        ax.spines[side].set_visible(False)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=2,
              frameon=False)
    ax.set_title("Best parameters within their bounds (ends: the bounds)", fontsize=10)
    return png(fig)


def failures(kinds: dict[str, int]) -> bytes:
    """Calls failed (by reason) and penalised (by physics check)."""
    fig = Figure(figsize=(8, 0.4 * max(len(kinds), 1) + 1.2))
    ax = fig.subplots()
    names = list(kinds)
    ax.barh(range(len(names)), [kinds[n] for n in names],
            color=["#d62728" if n.startswith("failed") else "#e69f00" for n in names])
    ax.set_yticks(range(len(names)), names)
    ax.invert_yaxis()
    ax.set_xlabel("calls")
    ax.set_title("Failed calls by reason, penalised calls by physics check", fontsize=10)
    return png(fig)


def forecast_fan(curves: pd.DataFrame, quantities: list[tuple[str, str]], history_end: float | None
                 ) -> bytes:
    """Field cumulatives of the forecast members: P90-P10 band, P50, members, truth, best."""
    fig = Figure(figsize=(4.2 * len(quantities), 3.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(quantities)))
    for ax, (q, title) in zip(axes, quantities):
        sel = curves[(curves.well == "FIELD") & (curves.quantity == q)]
        members = sel[sel.member.str.startswith(("call-", "draw-"))]
        if len(members):
            wide = members.pivot_table(index="days", columns="member", values="value")
            for m in wide.columns:
                ax.plot(wide.index, wide[m], color="#1f5fbf", lw=0.5, alpha=0.35)
            qs = np.nanquantile(wide.to_numpy(float), [0.1, 0.5, 0.9], axis=1)
            ax.fill_between(wide.index, qs[0], qs[2], color="#1f5fbf", alpha=0.2,
                            label="P90-P10 of members")
            ax.plot(wide.index, qs[1], color="#1f5fbf", lw=2, label="P50")
        for member in ("centre", "truth"):  # the truth last, on top of the P50
            ref = sel[sel.member == member].sort_values("days")
            if len(ref):
                ax.plot(ref.days, ref.value, **STYLE[member])
        if history_end is not None:
            ax.axvline(history_end, color="#444444", lw=1, ls="-.", label="end of fitted history")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("days since start")
        ax.set_ylabel(unit_of(sel, q))
        ax.grid(alpha=0.3)
    shared_legend(fig, axes, 1)
    return png(fig)
