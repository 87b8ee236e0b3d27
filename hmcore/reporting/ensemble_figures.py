"""The figures of an ensemble run's report as PNG bytes (matplotlib's object API, no pyplot).

Each function draws from arrays and tables already loaded (no simulator, no file reading):

* :func:`layer_maps`: one layer of one field, prior mean and standard deviation, posterior
  mean and standard deviation, and the truth when it is known (the means and the truth on one
  colour scale, the two standard deviations on another);
* :func:`well_ensembles`: one well's responses, every prior and posterior member as a thin
  line with the ensemble's P10-P90 band, against the observations and their noise band, the
  held-back period and the forecast shaded (the campaign report's helpers and style,
  :mod:`hmcore.reporting.figures`);
* :func:`misfit_boxes`: every member's data misfit per round of runs, one box each;
* :func:`forecast_fans`: cumulative curves of the prior and the posterior, each a P10-P90 band
  and its P50, the truth beside them when known.

Ensembles are told apart by colour everywhere: :data:`COLOURS`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from hmcore.reporting.figures import (
    STYLE,
    observed_points,
    panels_of,
    png,
    response_axis,
    shade_periods,
    shared_legend,
    unit_of,
)

COLOURS = {"prior": "#e69f00", "posterior": "#1f5fbf"}
"""The prior in orange, the posterior in blue (the campaign report's best case colour)."""
MAP_TITLES = ("prior mean", "prior std", "posterior mean", "posterior std", "truth")


def layer_maps(title: str, maps: Mapping[str, np.ndarray], unit: str) -> bytes:
    """One layer of one field: ``maps`` holds (ny, nx) arrays (NaN: inactive cell) under the
    keys of :data:`MAP_TITLES` (``truth`` optional); ``unit`` labels the colour bars."""
    names = [n for n in MAP_TITLES if n in maps]
    fig = Figure(figsize=(3.3 * len(names) + 0.8, 3.4))
    axes = np.atleast_1d(fig.subplots(1, len(names), squeeze=False)[0])
    means = [maps[n] for n in names if "std" not in n]
    stds = [maps[n] for n in names if "std" in n]
    scale = {"mean": _limits(means), "std": _limits(stds, low=0.0)}
    for ax, name in zip(axes, names):
        kind = "std" if "std" in name else "mean"
        lo, hi = scale[kind]
        image = ax.imshow(np.ma.masked_invalid(maps[name]), origin="upper", vmin=lo, vmax=hi,
                          cmap="viridis" if kind == "mean" else "magma",
                          interpolation="nearest")
        ax.set_title(name, fontsize=9)
        # cell indices at the map's edges only (i across, j down): tick labels on every
        # panel cost most of a map's drawing time
        ax.set_xticks([0, maps[name].shape[1] - 1], ["1", str(maps[name].shape[1])])
        ax.set_yticks([0, maps[name].shape[0] - 1], ["1", str(maps[name].shape[0])])
        ax.set_xlabel("i", fontsize=8, labelpad=-6)
        ax.set_ylabel("j", fontsize=8, labelpad=-8)
        ax.tick_params(labelsize=7, length=2)
        fig.colorbar(image, ax=ax, shrink=0.8).ax.tick_params(labelsize=7)
    fig.suptitle(f"{title} ({unit})", fontsize=10)
    return png(fig)


def _limits(arrays: Sequence[np.ndarray], low: float | None = None) -> tuple[float, float]:
    """The colour range over ``arrays``' finite values (``low`` fixed when given)."""
    values = np.concatenate([np.ravel(a)[np.isfinite(np.ravel(a))] for a in arrays]) \
        if arrays else np.zeros(0)
    if not values.size:
        return (0.0, 1.0)
    lo = float(values.min()) if low is None else low
    hi = float(values.max())
    return (lo, hi if hi > lo else lo + 1e-6)


def well_ensembles(well: str, observed: pd.DataFrame, curves: pd.DataFrame,
                   truth: pd.DataFrame | None, history_end: float | None) -> bytes:
    """One well's panels (a producer's six responses, an injector's rates and BHP).
    ``observed``: ObservationSet rows of this well; ``curves``: this well's rows of the
    members' curves (``ensemble``, ``member``, ``quantity``, ``days``, ``value``, ``unit``);
    ``truth``: the truth's curves of this well (``quantity``, ``days``, ``value``) or None."""
    end = float(curves.days.max()) if len(curves) else None
    panels = panels_of(observed, curves)
    rows = 2 if len(panels) > 3 else 1
    fig = Figure(figsize=(13, 6.6 if rows == 2 else 3.8))
    axes = fig.subplots(rows, 3, sharex=True, squeeze=False)
    fig.subplots_adjust(wspace=0.3)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    for ax, (q, title) in zip(axes.flat, panels):
        shade_periods(ax, observed, history_end, end)
        for ensemble, colour in COLOURS.items():
            sel = curves[(curves.ensemble == ensemble) & (curves.quantity == q)]
            _members_and_band(ax, sel, colour, ensemble)
        observed_points(ax, q, observed[observed.quantity == q].sort_values("days"))
        if truth is not None:
            ref = truth[truth.quantity == q].sort_values("days")
            if len(ref):
                ax.plot(ref.days, ref.value, **STYLE["truth"])
        ax.set_title(f"{well}: {title}", fontsize=10)
        ax.set_ylabel(unit_of(curves, q))
        response_axis(ax, q)
    for ax in axes[-1]:
        ax.set_xlabel("days since start")
    shared_legend(fig, axes, rows, ncol=5)
    return png(fig)


def _members_and_band(ax, sel: pd.DataFrame, colour: str, ensemble: str) -> None:
    """Every member of one ensemble as a thin line and its P10-P90 band."""
    if not len(sel):
        return
    wide = sel.pivot_table(index="days", columns="member", values="value", observed=True)
    days = wide.index.to_numpy(float)
    lines = [np.column_stack([days, wide[m].to_numpy(float)]) for m in wide.columns]
    # one artist for all members: a Line2D each made 100 members' report take 8 s a well
    ax.add_collection(LineCollection(lines, colors=colour, linewidths=0.5, alpha=0.35,
                                     label=f"{ensemble} members"))
    ax.autoscale_view()
    if wide.shape[1] > 1:
        lo, hi = quantiles(wide.to_numpy(float), (0.1, 0.9))
        ax.fill_between(wide.index, lo, hi, color=colour, alpha=0.2, lw=0,
                        label=f"{ensemble} P10-P90")


def quantiles(values: np.ndarray, qs: Sequence[float]) -> np.ndarray:
    """Quantiles ``qs`` over the members (columns) of ``values`` ``(times, members)``, NaN
    members ignored; NaN at a time where no member has a value (a ratio of a shut well)."""
    out = np.full((len(qs), values.shape[0]), np.nan)
    ok = np.isfinite(values).any(axis=1)
    if ok.any():
        out[:, ok] = np.nanquantile(values[ok], list(qs), axis=1)
    return out


def misfit_boxes(misfit: pd.DataFrame, labels: Mapping[int, str]) -> bytes:
    """Every member's data misfit (mean square whitened residual of the fitted history) per
    round of runs, one box each, on a log scale; ``labels`` names the rounds (0: the prior's
    runs). Failed members have no misfit and are counted in their round's label."""
    rounds = sorted(labels)
    data = [misfit.loc[(misfit.iteration == i) & np.isfinite(misfit.misfit), "misfit"]
            .to_numpy(float) for i in rounds]
    fig = Figure(figsize=(1.6 * len(rounds) + 3, 4))
    ax = fig.subplots()
    box = ax.boxplot([d[d > 0] for d in data], positions=list(range(len(rounds))), widths=0.5,
                     patch_artist=True, showfliers=True)
    for patch, i in zip(box["boxes"], rounds):
        patch.set_facecolor(COLOURS["prior"] if i == 0 else COLOURS["posterior"]
                            if i == rounds[-1] else "#9ab3dc")
        patch.set_alpha(0.6)
    notes = []
    for k, i in enumerate(rounds):
        failed = int(((misfit.iteration == i) & (misfit.status == "FAIL")).sum())
        notes.append(f"{labels[i]}\n{data[k].size} ran" + (f", {failed} failed" if failed
                                                            else ""))
    ax.axhline(1.0, color="#2e8b57", lw=1, ls=":", label="fits within the noise (1)")
    ax.set_yscale("log")
    ax.set_xticks(range(len(rounds)), notes, fontsize=8)
    ax.set_ylabel("data misfit (chi2/n, log scale)")
    ax.set_title("Data misfit of every member, per round of runs", fontsize=10)
    ax.grid(alpha=0.3, which="both", axis="y")
    ax.legend(fontsize=8)
    return png(fig)


def forecast_fans(curves: pd.DataFrame, targets: Sequence[tuple[str, str, str]],
                  truth: pd.DataFrame | None, history_end: float | None) -> bytes:
    """Cumulative curves of the prior and the posterior: per target ``(well, quantity,
    title)`` (FIELD for the field's totals) a P10-P90 band and the P50 of each ensemble, the
    truth's curve when ``truth`` (``well``, ``quantity``, ``days``, ``value``) has it, and the
    end of the fitted history."""
    cols = min(3, len(targets))
    rows = math.ceil(len(targets) / cols)
    fig = Figure(figsize=(4.6 * cols, 3.4 * rows + 0.4))
    axes = fig.subplots(rows, cols, squeeze=False)
    fig.subplots_adjust(hspace=0.45, wspace=0.35)
    for ax in axes.flat[len(targets):]:
        ax.set_visible(False)
    for ax, (well, q, title) in zip(axes.flat, targets):
        sel = curves[(curves.well == well) & (curves.quantity == q)]
        for ensemble, colour in COLOURS.items():
            part = sel[sel.ensemble == ensemble]
            if not len(part):
                continue
            wide = part.pivot_table(index="days", columns="member", values="value",
                                    observed=True)
            lo, mid, hi = quantiles(wide.to_numpy(float), (0.1, 0.5, 0.9))
            ax.fill_between(wide.index, lo, hi, color=colour, alpha=0.25, lw=0,
                            label=f"{ensemble} P10-P90")
            ax.plot(wide.index, mid, color=colour, lw=2, label=f"{ensemble} P50")
        if truth is not None:
            ref = truth[(truth.well == well) & (truth.quantity == q)].sort_values("days")
            if len(ref):
                ax.plot(ref.days, ref.value, **STYLE["truth"])
        if history_end is not None:
            ax.axvline(history_end, color="#444444", lw=1, ls="-.",
                       label="end of fitted history")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("days since start")
        ax.set_ylabel(unit_of(sel, q))
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    shared_legend(fig, axes, 2, ncol=6)
    return png(fig)
