"""``report.html``: one self-contained page (figures embedded as PNG data) and the same figures
as PNG files, from stored tables only (no simulator, no run directory).

The page is a jinja2 template (``hmcore/templates/report.html.j2``); the figures are
:mod:`hmcore.reporting.figures`'. Each figure is an ``<img data-figure=NAME>`` so a browser test can
check every expected one is there and loaded.
"""

from __future__ import annotations

import base64
import datetime as dt
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from jinja2 import Environment, FileSystemLoader, select_autoescape
from markdown_it import MarkdownIt
from markupsafe import Markup

from hmcore.ordering import natural_key
from hmcore.reporting import figures as figs
from hmcore.reporting.calls import Calls, calls_markdown, chart_counts, count_calls
from hmcore.reporting.identifiability import Finding, identifiability_markdown
from hmcore.reporting.report import (
    Choice,
    choice_markdown,
    convergence_markdown,
    has_heldout,
    heldout_markdown,
    information_markdown,
    marked_tables,
    truth_distance,
    well_names,
)
from hmcore.scoring.information import INFO_COLUMNS, informative_macro, uninformative
from hmcore.scoring.metrics import well_table
from hmcore.scoring.noise_table import noise_markdown

TEMPLATES = Path(__file__).parent / "templates"
FAN = [("FOPT", "field cumulative oil"), ("FWPT", "field cumulative water"),
       ("FGPT", "field cumulative gas")]


@dataclass(frozen=True)
class ReportInputs:
    """Everything the page is drawn from (the report task loads it from the store)."""

    campaign: str
    case_doc: dict
    agent: str
    table: pd.DataFrame                 # evaluations.parquet
    best: dict | None                   # the best case's metrics.json
    observed: pd.DataFrame | None       # ObservationSet rows (with sigma and period)
    history_end: float | None
    curves: pd.DataFrame | None         # curves.parquet
    forecast: pd.DataFrame | None       # forecast.parquet
    forecast_doc: dict | None           # forecast.json
    references: dict = field(default_factory=dict)  # "floor"/"centre" -> E
    truth: dict | None = None
    diagnosis_markdown: str | None = None
    diagnosis_figures: dict = field(default_factory=dict)  # name -> PNG bytes
    code: str = ""
    choice: Choice | None = None        # what chose the best call (records.json)
    noise: pd.DataFrame | None = None   # the noise the fit assumed (noise.parquet)
    information: pd.DataFrame | None = None  # hmcore.scoring.information.information_table
    identifiability: Finding | None = None  # hmcore.reporting.identifiability

    @property
    def calls(self) -> Calls:
        """The calls as valid, penalised, failed, by physics check and failure reason."""
        return count_calls(self.table, self.case_doc.get("physics"))


def expected_figures(inputs: ReportInputs) -> list[str]:
    """The figure names the page holds for these inputs (what a test checks is on the page)."""
    return list(_figures(inputs, draw=False))


def render(inputs: ReportInputs) -> tuple[str, dict[str, bytes]]:
    """(HTML, {figure file name: PNG bytes})."""
    pngs = _figures(inputs, draw=True)
    env = Environment(loader=FileSystemLoader(TEMPLATES), autoescape=select_autoescape(["j2"]))
    template = env.get_template("report.html.j2")

    def figure(name: str) -> Markup:
        data = base64.b64encode(pngs[name]).decode("ascii")
        caption = CAPTIONS.get(name.removesuffix(".png").split("__")[0], name)
        return Markup('<figure><img data-figure="{0}" alt="{1}" src="data:image/png;base64,'
                      '{2}"><figcaption>{1} ({0})</figcaption></figure>'
                      ).format(name, caption, Markup(data))

    names = list(pngs)
    t = inputs.table
    calls = inputs.calls
    html = template.render(
        figure=figure, campaign=inputs.campaign, case_name=inputs.case_doc["name"],
        case_source=inputs.case_doc.get("source", ""), agent=inputs.agent, calls=len(t),
        status_text=calls.text,
        built=dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        code=inputs.code, best=_best_card(inputs), references=_reference_cards(inputs),
        summary_figures=[n for n in names if n.startswith("cmatch")],
        well_figures=[n for n in names if n.startswith("well__")],
        convergence_figures=[n for n in names if n.startswith(("best_so_far", "failures"))],
        parameter_figures=[n for n in names if n.startswith("parameter")],
        forecast_figures=[n for n in names if n.startswith("forecast")],
        failure_counts=chart_counts(calls), best_params=_best_params(inputs),
        truth=inputs.truth, floor_label=_floor_label(inputs), forecast=_forecast(inputs),
        beyond_data=_beyond_data(inputs),
        paper_tables=_paper_tables(inputs), diagnosis=_diagnosis(inputs, names),
        sections=_sections(inputs, calls))
    return html, pngs


def markdown_html(text: str) -> str:
    """Markdown (CommonMark with tables, no raw HTML) as HTML."""
    return MarkdownIt("commonmark", {"html": False}).enable("table").render(text)


def _sections(inputs: ReportInputs, calls: Calls) -> dict[str, str]:
    """The report's sections written once as Markdown (:mod:`hmcore.reporting.report`), as
    HTML: ``choice``, ``information``, ``heldout``, ``calls``, ``convergence``,
    ``identifiability``, ``noise`` (a section the inputs do not allow is absent)."""
    parts: dict[str, list[str]] = {"calls": calls_markdown(calls)}
    best, info = inputs.best, _information(inputs)
    if best is not None:
        parts["choice"] = choice_markdown(best, inputs.choice or Choice(best.get(
            "objective", "E")))
        if best.get("metrics", {}).get("categories"):
            parts["information"] = information_markdown(best["metrics"], info, "fit",
                                                        well_names(best["metrics"]))
    if has_heldout(best):
        parts["heldout"] = heldout_markdown(best, inputs.case_doc, info,
                                            (inputs.choice or Choice()).references)
    if len(inputs.table) and "best_E_so_far" in inputs.table:
        parts["convergence"] = convergence_markdown(inputs.table, inputs.choice or Choice())
    if best is not None and inputs.identifiability is not None:
        parts["identifiability"] = identifiability_markdown(
            inputs.identifiability, inputs.case_doc.get("source", "CASE"), inputs.truth)
    if inputs.noise is not None and not inputs.noise.empty:
        parts["noise"] = [noise_markdown(inputs.noise)]
    return {k: markdown_html("\n".join(v) + "\n") for k, v in parts.items()}


def _information(inputs: ReportInputs) -> pd.DataFrame:
    """The inputs' information table (empty: every scored response counts)."""
    if inputs.information is not None:
        return inputs.information
    return pd.DataFrame(columns=INFO_COLUMNS)


CAPTIONS = {"well": "observed against simulated, six responses",
            "best_so_far": "best so far against simulator calls",
            "cmatch_heatmap": "C_match per well and response (best case)",
            "parameter_traces": "parameter values call by call",
            "parameters_vs_bounds": "best parameters within their bounds",
            "failures": "failed and penalised calls",
            "forecast_fan": "forecast of field cumulatives",
            "diagnosis": "diagnosis plot"}


def _figures(inputs: ReportInputs, draw: bool) -> dict[str, bytes]:
    out: dict[str, bytes] = {}

    def add(name: str, make) -> None:
        out[f"{name}.png"] = make() if draw else b""

    t, best = inputs.table, inputs.best
    bounds = {p["name"]: (float(p["low"]), float(p["high"]))
              for p in inputs.case_doc["parameters"]}
    if best is not None and best.get("metrics", {}).get("wells"):
        add("cmatch_heatmap", lambda: figs.cmatch_heatmap(
            well_table(best["metrics"]), uninformative(_information(inputs), "fit")))
    curves = inputs.curves
    if curves is not None and len(curves):
        for well in _wells(inputs):
            obs = (inputs.observed[inputs.observed.well == well] if inputs.observed is not None
                   else pd.DataFrame(columns=["quantity", "days", "observed", "sigma"]))
            add(f"well__{safe_name(well)}", lambda w=well, o=obs: figs.well_curves(
                w, plottable_observed(o), plottable_curves(curves[curves.well == w]),
                inputs.history_end))
    if len(t):
        choice = inputs.choice or Choice()
        add("best_so_far", lambda: figs.best_so_far(
            t, inputs.references.get("floor"), inputs.references.get("centre"),
            choice.objective, choice.references))
        kinds = chart_counts(inputs.calls)
        if kinds:
            add("failures", lambda: figs.failures(kinds))
        add("parameter_traces", lambda: figs.parameter_traces(
            t, bounds, best["params"] if best else None))
    if best is not None:
        add("parameters_vs_bounds", lambda: figs.best_against_bounds(bounds, best["params"],
                                                                     inputs.truth))
    if inputs.forecast is not None and len(inputs.forecast) and curves is not None:
        add("forecast_fan", lambda: figs.forecast_fan(curves, FAN, inputs.history_end))
    for name, data in inputs.diagnosis_figures.items():
        out[f"diagnosis__{name}"] = data
    return out


def _wells(inputs: ReportInputs) -> list[str]:
    wells = [w for w in inputs.case_doc.get("wells", []) if w in set(inputs.curves.well)]
    return sorted(wells, key=natural_key)



def safe_name(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)


def plottable_observed(obs: pd.DataFrame) -> pd.DataFrame:
    """GOR and water cut only while the well flows (they are undefined when it is shut)."""
    if "flowing" in obs:
        return obs[obs.flowing.astype(bool) | ~obs.quantity.isin(["WGOR", "WWCT"])]
    return obs


def plottable_curves(curves: pd.DataFrame) -> pd.DataFrame:
    """Simulated GOR and water cut where the well produces oil, BHP where it is a pressure (a
    summary reports 0 before the well exists)."""
    out = curves.copy()
    oil = out[out.quantity == "WOPR"][["member", "days", "value"]].rename(
        columns={"value": "oil"})
    out = out.merge(oil, on=["member", "days"], how="left")
    ratio = out.quantity.isin(["WGOR", "WWCT"]) & ~(out.oil > 0)
    out.loc[ratio | ((out.quantity == "WBHP") & ~(out.value > 0)), "value"] = np.nan
    return out.drop(columns="oil")


def _fmt(v, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    v = float(v)
    return f"{v:.{digits}g}" if abs(v) < 1e-3 or abs(v) >= 1e5 else f"{v:.{digits}f}"


def volume_text(v) -> str:
    """A cumulative volume as engineers read one: 1,685,000 (4 significant digits)."""
    if v is None or not math.isfinite(float(v)):
        return ""
    v = float(v)
    if abs(v) < 1000:
        return f"{v:.4g}"
    digits = int(math.floor(math.log10(abs(v)))) + 1
    return f"{round(v, 4 - digits):,.0f}"


def _best_card(inputs: ReportInputs) -> dict | None:
    """The summary cards of the best case: E, likelihood, the macro scores over the responses
    that carry information (and which) and the paper's macro C_match."""
    b = inputs.best
    if b is None:
        return None
    metrics = b.get("metrics", {})
    macro = metrics.get("macro", {})
    mine = informative_macro(metrics, _information(inputs), "fit") if metrics.get(
        "categories") else {**macro, "includes": []}
    lk = b.get("likelihood")
    eh = b.get("E_heldout")
    return {"E": f"{b['E']:.6g}", "call": b["index"] + 1, "nmse": _fmt(mine.get("nmse")),
            "r2": _fmt(mine.get("r2")), "cmatch": _fmt(mine.get("cmatch"), 2),
            "includes": ", ".join(mine["includes"]),
            "paper_cmatch": _fmt(macro.get("cmatch"), 2),
            "E_heldout": f"{eh:.6g}" if eh is not None and math.isfinite(eh) else None,
            "likelihood": f"{lk:.6g}" if lk is not None and math.isfinite(lk) else None,
            "chosen": b.get("objective", "E")}


def _floor_label(inputs: ReportInputs) -> str | None:
    if inputs.curves is None:
        return None
    members = set(inputs.curves.member)
    return "truth" if "truth" in members else "deck's own values" if "deck" in members else None


def _reference_cards(inputs: ReportInputs) -> list[dict]:
    label = {"floor": ("E of the truth" if inputs.truth else "E of the deck's own values"),
             "centre": "E of the prior centre"}
    return [{"E": f"{v:.6g}", "label": label[k]} for k, v in inputs.references.items()
            if v is not None and math.isfinite(v)]


def _best_params(inputs: ReportInputs) -> list[dict]:
    """The best case's parameters with their bounds and, against a known truth, the truth,
    the error and the error as a share of the range."""
    if inputs.best is None:
        return []
    dist = truth_distance(inputs.case_doc, inputs.best["params"], inputs.truth or {})
    rows = []
    for p in inputs.case_doc["parameters"]:
        name = p["name"]
        d = dist.get(name, {})
        rows.append({"name": name, "value": _fmt(inputs.best["params"].get(name)),
                     "low": _fmt(p["low"]), "high": _fmt(p["high"]),
                     "truth": _fmt((inputs.truth or {}).get(name)), "error": _fmt(d.get("error")),
                     "error_of_range": _fmt(d.get("error_of_range"), 3)})
    return rows


def _beyond_data(inputs: ReportInputs) -> bool:
    """Whether the runs go on past the last observation (a forecast period with no data);
    True when it cannot be told (no curves or no history stored)."""
    curves, observed = inputs.curves, inputs.observed
    if curves is None or not len(curves) or observed is None or not len(observed):
        return True
    return float(curves.days.max()) > float(observed.days.max()) + 0.5


def _posterior_words(post: dict | None) -> str:
    """What the posterior draws were, in one sentence (empty without draws)."""
    if not post:
        return ""
    free = post.get("free") or []
    inflation = post.get("inflation") or 1.0
    return (f"{post.get('asked')} parameter sets drawn from the Laplace posterior at call "
            f"{post.get('best_call')} (from {post.get('tried')} tries: the rest fell outside the "
            f"box or broke a physics check), simulated after the fit, apart from the budget; "
            f"{post.get('valid')} ran valid and make the band."
            + (f" The best call's residuals are {inflation:.3g} times the noise's variance "
               "(chi2 over n - d), so the covariance is widened by that factor."
               if inflation > 1.0 else "")
            + (f" The data do not determine {', '.join(free)}: drawn across the box."
               if free else ""))


def _forecast(inputs: ReportInputs) -> dict | None:
    f, doc = inputs.forecast, inputs.forecast_doc
    if f is None or not len(f) or doc is None:
        return None
    show = f[["label", "members", "P90", "P50", "P10", "truth", "truth_inside"]].copy()
    unit = {}
    if inputs.curves is not None:
        unit = (inputs.curves.drop_duplicates("quantity").set_index("quantity")["unit"]
                .str.lower().to_dict())
    show.insert(1, "unit", [unit.get(q, "") for q in f.quantity])
    for c in ("P90", "P50", "P10", "truth"):
        show[c] = [volume_text(v) for v in show[c]]
    show["truth_inside"] = [{True: "yes", False: "NO"}.get(v, "") for v in show.truth_inside]
    if not doc.get("truth_run", doc.get("truth_known")):
        show = show.drop(columns=["truth", "truth_inside"])
    else:
        show = show.rename(columns={"truth_inside": "truth in [P90, P10]"})
    calls = doc.get("member_calls", []) or doc.get("member_draws", [])
    chosen_by = doc.get("objective") if doc.get("kind") == "near_best" else None
    return {"caveat": doc["caveat"], "members": len(calls), "chosen_by": chosen_by,
            "posterior": _posterior_words(doc.get("posterior")),
            "calls": ", ".join(str(c) for c in calls),
            "end_days": f"{float(f.end_days.max()):g}",
            "table": show.to_html(index=False, border=0, classes="forecast",
                                  table_id="forecast-table")}


def _paper_tables(inputs: ReportInputs) -> list[dict]:
    """The paper's three tables of the fitted history, marked where a response carries no
    information (:func:`hmcore.reporting.report.marked_tables`)."""
    if inputs.best is None or not inputs.best.get("metrics", {}).get("categories"):
        return []
    heads = {"categories": "Match by category", "wells": "C_match (%) per well and category",
             "ratios": "GOR and water cut per well: records used, left out and why"}
    tables = marked_tables(inputs.best["metrics"], _information(inputs), "fit")
    return [{"title": heads[k], "html": df.to_html(index=False, border=0, na_rep="n/a")}
            for k, df in tables.items()]


def _diagnosis(inputs: ReportInputs, names: list[str]) -> dict | None:
    if inputs.diagnosis_markdown is None:
        return None
    text = "\n".join(line for line in inputs.diagnosis_markdown.splitlines()
                     if not line.startswith("![")) + "\n"  # figures are embedded below
    return {"html": markdown_html(text),
            "figures": [n for n in names if n.startswith("diagnosis__")]}
