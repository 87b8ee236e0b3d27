"""The report of an ensemble run (``hmflow ensemble``, issue 41), from what the run stored.

Drawn from arrays and tables the report task has read from the store (the prior and the
posterior ensembles, the grid's active cells, the observation rows, every member's curves and
misfit, the forecast table), and from the case's truth when its folder holds one: nothing
here runs a simulator or reads a run directory. :func:`build` returns ``report.md``,
``report.html`` (one self-contained page, the figures embedded), ``report.json`` and the PNG
figures (:mod:`hmcore.reporting.ensemble_figures`):

* per field and grid layer, maps of the prior and posterior mean and standard deviation in
  the field's update space (log10 for permeability), and the truth's when known;
* per well, the prior and posterior members' responses against the observations;
* every member's data misfit per round of runs, one box per round;
* the forecast fans (FOPT and each well's cumulative oil) and the P90/P50/P10 table, with the
  truth's value and whether it lies inside [P90, P10] when known.

The truth, when the case's folder holds one: :mod:`hmcore.reporting.ensemble_truth`.
"""

from __future__ import annotations

import base64
import datetime as dt
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from markdown_it import MarkdownIt

from hmcore.fields.spec import FieldSpec
from hmcore.fields.spread import COLLAPSED, FieldSpread, field_spread, kept
from hmcore.ordering import natural_key
from hmcore.reporting import ensemble_figures as figs
from hmcore.reporting.ensemble_truth import FieldTruth
from hmcore.reporting.html import plottable_curves, plottable_observed, safe_name, volume_text
from hmcore.simulation.curves import FIELD
from hmcore.simulation.forecast import inside_band

REPORT_VERSION = 2  # 2: the fields' spread table (2026-11-28)
"""Bump when the report's content changes for the same stored run."""


@dataclass(frozen=True, eq=False)
class EnsembleReportInputs:
    """Everything the report is drawn from. ``prior`` / ``posterior``: field name ->
    ``(members, n_active)`` in update space (a member left out is a row of NaN); ``active``:
    the active cells' global indices in a grid of ``dims`` (nx, ny, nz); ``observed``: the
    ObservationSet rows (``well, quantity, days, observed, sigma, period, flowing``);
    ``curves``, ``misfit``, ``forecast``, ``summary``: the forecast step's tables
    (:func:`tasks.ensemble.member_curves`, ``member_misfits``, ``forecast.parquet``,
    ``summary.json``)."""

    campaign: str
    case_name: str
    case_source: str
    fields: tuple[FieldSpec, ...]
    dims: tuple[int, int, int]
    active: np.ndarray
    prior: Mapping[str, np.ndarray]
    posterior: Mapping[str, np.ndarray]
    observed: pd.DataFrame
    history_end: float | None
    curves: pd.DataFrame
    misfit: pd.DataFrame
    forecast: pd.DataFrame
    summary: dict
    wells: tuple[str, ...]
    weights: tuple[float, ...] = ()
    truth: FieldTruth | None = None
    code: str = ""


@dataclass(frozen=True)
class EnsembleReport:
    """The report's files: ``markdown``, ``html``, ``doc`` (report.json) and ``figures``
    (file name -> PNG bytes, in the order they appear)."""

    markdown: str
    html: str
    doc: dict
    figures: dict[str, bytes] = field(default_factory=dict)


# ------------------------------------------------------------------------------ maps
def to_layers(values: np.ndarray, dims: tuple[int, int, int], active: np.ndarray) -> np.ndarray:
    """Per-active-cell ``values`` ``(n_active,)`` as ``(nz, ny, nx)`` (NaN where inactive)."""
    nx, ny, nz = dims
    full = np.full(nx * ny * nz, np.nan)
    full[np.asarray(active, np.int64)] = values
    return full.reshape(nz, ny, nx)


def mean_and_std(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation (ddof 1; 0 for one member) over the members of ``X``
    ``(members, n)`` that are not left out (rows with a NaN)."""
    n = np.shape(X)[1]
    members = kept(X)
    if not len(members):
        return np.full(n, np.nan), np.full(n, np.nan)
    std = members.std(axis=0, ddof=1) if len(members) > 1 else np.zeros(n)
    return members.mean(axis=0), std


def field_layer_maps(inputs: EnsembleReportInputs, name: str) -> list[dict[str, np.ndarray]]:
    """Per layer (k = 1..nz) of field ``name``: {map title: (ny, nx)} of
    :data:`~hmcore.reporting.ensemble_figures.MAP_TITLES` (truth when known)."""
    stats = {}
    for ensemble in ("prior", "posterior"):
        mean, std = mean_and_std(getattr(inputs, ensemble)[name])
        stats[f"{ensemble} mean"] = to_layers(mean, inputs.dims, inputs.active)
        stats[f"{ensemble} std"] = to_layers(std, inputs.dims, inputs.active)
    if inputs.truth is not None and name in inputs.truth.fields:
        stats["truth"] = to_layers(inputs.truth.fields[name], inputs.dims, inputs.active)
    return [{title: layers[k] for title, layers in stats.items()}
            for k in range(inputs.dims[2])]


def map_unit(spec: FieldSpec) -> str:
    """What a field's map shows: log10 of the value for a field updated in log space."""
    return f"log10 {spec.keyword}" if spec.in_log else spec.keyword


# ------------------------------------------------------------------------------ tables
def forecast_with_truth(forecast: pd.DataFrame, truth: pd.DataFrame | None) -> pd.DataFrame:
    """The forecast table (one row per ensemble and quantity) with ``truth`` (the truth's
    value at the forecast's end, from the truth's curve at its last day up to then) and
    ``truth_inside`` (truth in [P90, P10]); both None when the truth is unknown."""
    out = forecast.copy()
    values, inside = [], []
    for row in out.itertuples():
        t = float("nan")
        if truth is not None:
            sel = truth[(truth.well == row.well) & (truth.quantity == row.quantity)
                        & (truth.days <= float(row.end_days) + 1e-6)].sort_values("days")
            t = float(sel.value.iloc[-1]) if len(sel) else t
        values.append(t if math.isfinite(t) else None)
        inside.append(inside_band(row.P90, row.P10, t) if math.isfinite(t) else None)
    return out.assign(truth=values, truth_inside=inside)


def round_labels(summary: dict) -> dict[int, str]:
    """Round of runs -> its name: the prior, after update i, the posterior (the last)."""
    rounds = [it["iteration"] for it in summary.get("iterations", [])]
    last = max(rounds) if rounds else 0
    return {i: "prior" if i == 0 else "posterior" if i == last else f"after update {i}"
            for i in rounds}


def forecast_targets(inputs: EnsembleReportInputs) -> list[tuple[str, str, str]]:
    """The fans: the field's cumulative oil, then each well's that the curves hold with oil
    produced (an injector's is left out)."""
    c = inputs.curves
    oil = c[c.quantity.isin(["FOPT", "WOPT"]) & (c.value > 0)]
    have = set(zip(oil.well.astype(str), oil.quantity.astype(str)))
    targets = [(FIELD, "FOPT", "field cumulative oil (FOPT)")]
    return [t for t in targets + [(w, "WOPT", f"{w}: cumulative oil") for w in inputs.wells]
            if (t[0], t[1]) in have]


# ------------------------------------------------------------------------------ the figures
def expected_figures(inputs: EnsembleReportInputs) -> list[str]:
    """The figure file names the report holds for these inputs, in page order."""
    return list(_figures(inputs, draw=False))


def _figures(inputs: EnsembleReportInputs, draw: bool) -> dict[str, bytes]:
    out: dict[str, bytes] = {}

    def add(name: str, make) -> None:
        out[f"{name}.png"] = make() if draw else b""

    if len(inputs.misfit):
        add("misfit_boxes", lambda: figs.misfit_boxes(inputs.misfit,
                                                      round_labels(inputs.summary)))
    targets = forecast_targets(inputs)
    truth = inputs.truth.curves if inputs.truth is not None else None
    if targets:
        add("forecast_fans", lambda: figs.forecast_fans(inputs.curves, targets, truth,
                                                        inputs.history_end))
    for well in inputs.wells:
        if not (inputs.curves.well == well).any():
            continue
        add(f"well__{safe_name(well)}", lambda w=well: _well_figure(inputs, w, truth))
    for spec in inputs.fields:
        if spec.name not in inputs.prior or spec.name not in inputs.posterior:
            continue
        maps = field_layer_maps(inputs, spec.name) if draw else [{}] * inputs.dims[2]
        for k, layer in enumerate(maps, start=1):
            add(f"map__{safe_name(spec.name)}__k{k:02d}", lambda m=layer, k=k, s=spec:
                figs.layer_maps(f"{s.name}, layer k = {k}", m, map_unit(s)))
    return out


def _well_figure(inputs: EnsembleReportInputs, well: str, truth: pd.DataFrame | None) -> bytes:
    """One well's panels: the members' curves as the campaign report masks them (GOR and
    water cut only while oil flows, BHP only where positive)."""
    curves = inputs.curves[inputs.curves.well == well].astype(
        {"ensemble": str, "quantity": str, "unit": str, "well": str})
    keyed = curves.assign(member=curves.ensemble + "-" + curves.member.astype(str))
    masked = plottable_curves(keyed).assign(member=curves.member.to_numpy())
    obs = inputs.observed[inputs.observed.well == well]
    t = truth[truth.well == well] if truth is not None else None
    return figs.well_ensembles(well, plottable_observed(obs), masked, t, inputs.history_end)


# ------------------------------------------------------------------------------ the report
def build(inputs: EnsembleReportInputs) -> EnsembleReport:
    """report.md, report.html, report.json and the figures (see the module's docstring)."""
    pngs = _figures(inputs, draw=True)
    table = forecast_with_truth(inputs.forecast, inputs.truth.curves
                                if inputs.truth is not None else None)
    markdown = _markdown(inputs, table, list(pngs))
    doc = {"campaign": inputs.campaign, "kind": "ensemble", "report_version": REPORT_VERSION,
           "case": inputs.case_name, "figures": list(pngs),
           "truth": inputs.truth.source if inputs.truth is not None else None,
           "truth_fields": sorted(inputs.truth.fields) if inputs.truth is not None else [],
           "forecast": table.to_dict(orient="records"),
           "iterations": inputs.summary.get("iterations", []),
           "runs": inputs.summary.get("runs"), "failed": inputs.summary.get("failed"),
           "headline": inputs.summary.get("headline"),
           "fields": [{k: v if not isinstance(v, float) or math.isfinite(v) else None
                       for k, v in {**x.__dict__, "kept": x.kept}.items()}
                      | {"collapsed": x.collapsed, "prior_holds_truth": x.prior_holds_truth}
                      for x in field_spreads(inputs)]}
    return EnsembleReport(markdown, _html(inputs, markdown, pngs), doc, pngs)


def _markdown(inputs: EnsembleReportInputs, table: pd.DataFrame, names: list[str]) -> str:
    s = inputs.summary
    weights = ", ".join(f"{w:g}" for w in inputs.weights)
    lines = [f"# hmflow ensemble `{inputs.campaign}`", "",
             f"Case **{inputs.case_name}** ({inputs.case_source}); ES-MDA"
             + (f" with weights {weights}" if weights else "")
             + f"; {s.get('runs', 0)} member runs ({s.get('failed', 0)} failed). Rebuilt by "
             f"`hmflow report --campaign {inputs.campaign}` from the stored run, with no "
             f"simulator call; hmflow {inputs.code}.", ""]
    truth = inputs.truth
    lines += [f"Truth: {truth.source}" + (f" (fields {', '.join(sorted(truth.fields))})"
                                          if truth.fields else " (responses only)")
              if truth is not None else "Truth: unknown (no truth file beside the case).", ""]
    lines += ["## Data misfit per round of runs", "",
              ("The mean square of the noise-whitened residuals of the fitted history (about 1 "
               "for a model that fits within the noise)."), "",
              "| round | planned | ran | failed | median misfit | mean misfit |",
              "|---|---:|---:|---:|---:|---:|"]
    labels = round_labels(s)
    for it in s.get("iterations", []):
        lines.append(f"| {labels.get(it['iteration'], it['iteration'])} | {it['planned']} | "
                     f"{it['ran']} | {it['failed']} | {_num(it.get('misfit_median'))} | "
                     f"{_num(it.get('misfit_mean'))} |")
    lines += [""] + _images(names, "misfit_boxes", "data misfit per round")
    lines += ["## Forecast at the schedule's end", "",
              ("P90 is the low case (90 % of the members at or above it), P10 the high case; "
               "the members are the runs of the prior and of the posterior ensemble over the "
               "whole schedule."), "", _forecast_markdown(table, truth is not None and
                                                   truth.curves is not None), ""]
    lines += _images(names, "forecast_fans", "forecast fans")
    lines += ["## Wells: the ensembles against the observations", "",
              ("Every member a thin line (prior orange, posterior blue) with its ensemble's "
               "P10-P90 band; observed points with their noise band (+/- 1 sigma); shaded: the "
               "held-back period (measured, not fitted) and the forecast (no data)."), ""]
    lines += _images(names, "well__", "well")
    lines += ["## Fields, layer by layer", "",
              ("Prior and posterior mean and standard deviation over the members (log10 for a "
               "field updated in log space), and the truth when known."), "",
              spread_markdown(field_spreads(inputs)), ""]
    lines += _images(names, "map__", "field map")
    return "\n".join(lines) + "\n"


def field_spreads(inputs: EnsembleReportInputs) -> list[FieldSpread]:
    """Each field's spread, prior and posterior, against the truth's field when known."""
    truth = inputs.truth.fields if inputs.truth is not None else {}
    return [field_spread(f.name, inputs.prior[f.name], inputs.posterior[f.name],
                         truth.get(f.name), "log10" if f.in_log else "value")
            for f in inputs.fields if f.name in inputs.prior and f.name in inputs.posterior]


def spread_markdown(spreads: list[FieldSpread]) -> str:
    """The spread kept per field; with a truth, the RMSE of each mean to it and the RMSE over
    the spread (about 1 for a truth like a member; above :data:`COLLAPSED`, collapsed)."""
    known = any(math.isfinite(x.rmse_prior) for x in spreads)
    head = ["field", "space", "spread prior", "spread posterior", "kept"]
    head += ["RMSE of the mean prior", "posterior", "RMSE/spread prior", "posterior",
             "collapsed"] if known else []
    out = ["The spread: the root of the mean over cells of the members' variance. Data "
           "narrow a field where they inform it; an ensemble of few members also narrows it "
           "where they do not (spurious correlations, which localisation limits)"
           + (f"; against the truth, RMSE/spread is about 1 for a truth like a member, above "
              f"{COLLAPSED:g} the prior misses the truth, and a posterior's above {COLLAPSED:g} "
              "times the prior's (at least 1) is surer than it is right: the update collapsed "
              "it." if known else "."), "",
           "| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    for x in spreads:
        cells = [x.field, x.space, _num(x.sd_prior), _num(x.sd_posterior),
                 f"{x.kept:.0%}" if math.isfinite(x.kept) else "n/a"]
        if known:
            ratio = x.error_to_spread
            cells += [_num(x.rmse_prior), _num(x.rmse_posterior), _ratio(ratio[0]),
                      _ratio(ratio[1]), ("**yes**" if x.collapsed else "no")
                      + ("" if x.prior_holds_truth else " (the prior misses the truth)")]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def _ratio(v: float) -> str:
    return "inf" if v == math.inf else "n/a" if not math.isfinite(v) else f"{v:.2f}"


def _images(names: list[str], prefix: str, caption: str) -> list[str]:
    return [f"![{caption}: {n.removesuffix('.png').replace('__', ' ')}]({n})\n" for n in names
            if n.startswith(prefix)]


def _num(v) -> str:
    return "n/a" if v is None or not math.isfinite(float(v)) else f"{float(v):.4g}"


def _forecast_markdown(table: pd.DataFrame, truth_known: bool) -> str:
    head = ["quantity", "ensemble", "members", "P90", "P50", "P10"]
    head += ["truth", "truth in [P90, P10]"] if truth_known else []
    out = ["| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    order = table.assign(_w=[natural_key(str(w)) if w != FIELD else ("",) for w in table.well])
    for r in order.sort_values(["_w", "quantity", "ensemble"], ascending=[True, True, False],
                               kind="stable").itertuples():
        cells = [str(r.label), str(r.ensemble), str(int(r.members)),
                 *(volume_text(getattr(r, p)) for p in ("P90", "P50", "P10"))]
        if truth_known:
            cells += [volume_text(r.truth) if r.truth is not None else "n/a",
                      {True: "yes", False: "NO"}.get(r.truth_inside, "n/a")]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


STYLE = """body{font-family:system-ui,sans-serif;margin:0 auto;max-width:1280px;padding:1.5em;
color:#222;line-height:1.45}h2{border-bottom:2px solid #1f5fbf;padding-bottom:.2em;margin-top:2em}
table{border-collapse:collapse;margin:.8em 0;font-size:.9em}th,td{border:1px solid #ddd;
padding:.25em .6em;text-align:right}th{background:#f3f5f9}td:first-child,th:first-child{
text-align:left}img{max-width:100%;border:1px solid #eee;display:block;margin:1em 0}"""


def _html(inputs: EnsembleReportInputs, markdown: str, pngs: dict[str, bytes]) -> str:
    """The Markdown as one page, each figure embedded (``<img data-figure=NAME>``)."""
    body = MarkdownIt("commonmark", {"html": False}).enable("table").render(markdown)
    for name, data in pngs.items():
        encoded = base64.b64encode(data).decode("ascii")
        body = body.replace(f'src="{name}"',
                            f'data-figure="{name}" src="data:image/png;base64,{encoded}"')
    built = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>hmflow '
            f"ensemble {inputs.campaign}</title><style>{STYLE}</style></head><body>\n{body}"
            f'<p style="color:#555">built {built}</p></body></html>\n')
