"""Plain-text renderings of results: the campaign report with the paper's three tables as
Markdown, metrics as JSON.

Nothing here runs a simulator; everything is rebuilt from stored metrics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from hmcore.diagnosis.report import markdown_report
from hmcore.ordering import natural_key
from hmcore.reporting import paper_tables
from hmcore.reporting.calls import calls_markdown, count_calls
from hmcore.reporting.identifiability import (
    Finding,
    identifiability_document,
    identifiability_markdown,
)
from hmcore.scoring.information import (
    INFO_COLUMNS,
    information_grid,
    informative_macro,
    uninformative,
)
from hmcore.scoring.metrics import category_table, macro_categories, ratio_table, well_table
from hmcore.scoring.noise import Z_BEYOND_NOISE
from hmcore.scoring.noise_table import noise_markdown
from storage.jsonable import to_jsonable


def _fmt(v: Any, digits: int = 4) -> str:
    if isinstance(v, (float, np.floating)):
        return "n/a" if not math.isfinite(v) else f"{v:.{digits}g}" if abs(v) < 1e-3 else f"{v:.{digits}f}"
    return str(v)


def metrics_markdown(metrics: dict, title: str = "Match quality",
                     info: pd.DataFrame | None = None, period: str = "fit") -> str:
    """The paper's three tables (see :mod:`hmcore.reporting.paper_tables`), marked where a
    response of ``period`` carries no information (:func:`marked_tables`)."""
    return paper_tables.markdown(marked_tables(metrics, info, period), title)


def metrics_document(ev) -> dict:
    """The ``metrics.json`` document of one evaluation (see hmcore.scoring.evaluation.Evaluation)."""
    m = ev.metrics or {"macro": {}, "categories": {}, "wells": {}}
    doc = {
        "status": ev.status.value if hasattr(ev.status, "value") else ev.status,
        "reason": ev.reason,
        "params": ev.params,
        "macro": m.get("macro", {}),
        "categories": m.get("categories", {}),
        "wells": m.get("wells", {}),
        "excluded": m.get("excluded", {}),
        "misfit": {"E": ev.E, "penalty": ev.penalty, "reward": ev.reward,
                   "per_response": ev.per_response, "coverage": ev.coverage,
                   "E_heldout": ev.E_heldout},
        "heldout": ev.heldout_metrics,
        "run_dir": ev.run_dir,
        "sim_time_s": ev.sim_time_s,
        "wall_time_s": ev.wall_time_s,
        "peak_rss_bytes": ev.peak_rss_bytes,
    }
    return to_jsonable(doc)


def parameter_distance(found: dict[str, float], truth: dict[str, float],
                       bounds: dict[str, tuple[float, float]]) -> dict:
    """Per-parameter error and the error as a fraction of the parameter's range."""
    out = {}
    for name, t in truth.items():
        if name in found and name in bounds:
            lo, hi = bounds[name]
            out[name] = {"found": found[name], "truth": t, "error": found[name] - t,
                         "error_of_range": abs(found[name] - t) / (hi - lo)}
    return out


OBJECTIVE_WORDS = {
    "likelihood": "the likelihood (chi2/n: the mean square of the noise-whitened residuals of "
                  "the fitted history; 1 fits within the noise)",
    "E": "E (the paper's misfit)"}
E_WORDS = ("E, the reference paper's misfit: per response (BHP, oil, water, gas rates, pooled "
           "over the wells) the mean squared error of the simulated against the observed "
           "values divided by the observed range, averaged over the responses; 0 is a "
           "perfect match, and the noise is not in it. The paper's scores per response and well: "
           "NMSE = sum (y - yhat)^2 / sum y^2, R^2, and C_match = 100 / (1 + NMSE), 100 % "
           "a perfect match.")


@dataclass(frozen=True)
class Choice:
    """What chose the best call: the campaign's ``objective`` (``likelihood`` or ``E``), the
    noise it ended with (``noise``: which refinement, from which call) and the reference runs
    scored by it (``references``: floor and centre, each E and likelihood)."""

    objective: str = "E"
    noise: dict | None = None
    references: dict | None = field(default=None)


def choice_markdown(best: dict, choice: Choice) -> list[str]:
    """The best call's two numbers side by side, saying which chose it, with the floor's."""
    lines = [f"Chosen by {OBJECTIVE_WORDS.get(choice.objective, choice.objective)}.", "",
             "| | likelihood (chi2/n) | E |", "|---|---|---|"]
    mark = {"likelihood": ("**", ""), "E": ("", "**")}.get(choice.objective, ("", ""))

    def row(label: str, doc: dict) -> str:
        lk, e = (_fmt(float(v), 6) if v is not None else "n/a"
                 for v in (doc.get("likelihood"), doc.get("E")))
        return f"| {label} | {mark[0]}{lk}{mark[0]} | {mark[1]}{e}{mark[1]} |"

    lines.append(row(f"best (call {best['index'] + 1})", best))
    for label, doc in (choice.references or {}).items():
        lines.append(row({"floor": "truth / deck values", "centre": "prior centre"}.get(
            label, label), doc))
    lines += ["", E_WORDS]
    noise = choice.noise or {}
    if noise.get("prior"):
        lines += ["", f"The likelihood here includes the prior of the {len(noise['prior'])} "
                  "latent coefficients (standard normal a priori): (chi2 + sum z^2) / n, "
                  "-2 log-posterior per row, which the best call minimises."]
    if noise.get("refinement"):
        lines += ["", f"The likelihood is under the noise refined {noise['refinement']} time(s) "
                  f"from the fit's residuals, last from call {noise['refined_from_call'] + 1}."]
    return lines + [""]


def build_report(campaign: str, case_doc: dict, table: pd.DataFrame | None, best: dict | None,
                 truth: dict[str, float] | None,
                 diagnosis: dict | None = None,
                 noise: pd.DataFrame | None = None,
                 choice: Choice | None = None,
                 information: pd.DataFrame | None = None,
                 identifiability: Finding | None = None) -> tuple[str, dict]:
    """Markdown report and its JSON twin from stored results (no simulator involved).

    ``table``: the consolidated evaluations (None: the campaign ran no calibration, e.g. a
    diagnosis alone); ``diagnosis``: the campaign's latest ``diagnosis.json``, appended as a
    section (its plots are linked by file name, stored beside the report); ``noise``: the
    noise the fit assumed (:func:`hmcore.scoring.noise_table.noise_summary`, stored with the
    campaign's case, or its latest refinement), a section of its own; ``choice``: what chose
    the best call (default: E, as campaigns did before the objective); ``information``: which
    responses carry information (:func:`hmcore.scoring.information.information_table`; None:
    every scored response counts); ``identifiability``: what the data pin down at the best
    call (:func:`hmcore.reporting.identifiability.load_identifiability`; None: no section)."""
    choice = choice or Choice()
    if table is None:
        markdown = "\n".join([f"# hmflow campaign `{campaign}`", "",
                               f"Case **{case_doc['name']}** ({case_doc['source']}); no "
                               "calibration campaign was run under this name.", ""]) + "\n"
        doc: dict = {"campaign": campaign, "case": case_doc["name"], "calls": 0, "best": None}
    else:
        info = information if information is not None else pd.DataFrame(columns=INFO_COLUMNS)
        markdown, doc = _campaign_report(campaign, case_doc, table, best, truth, choice, info,
                                         identifiability)
    if noise is not None and not noise.empty:
        markdown += "\n" + noise_markdown(noise)
        doc["noise"] = to_jsonable(noise.to_dict(orient="records"))
    if diagnosis is not None:
        markdown += "\n" + markdown_report(diagnosis, level=2)
        sel = diagnosis.get("selected")
        doc["diagnosis"] = {"verdict": diagnosis["verdict"], "gain": diagnosis["gain"],
                            "selected": None if sel is None else sel["id"],
                            "causes": [c["id"] for c in diagnosis["causes"][:10]],
                            "plots": diagnosis.get("plots", [])}
    return markdown, to_jsonable(doc)


def _campaign_report(campaign: str, case_doc: dict, table: pd.DataFrame, best: dict | None,
                     truth: dict[str, float] | None, choice: Choice, info: pd.DataFrame,
                     identifiability: Finding | None = None) -> tuple[str, dict]:
    n = len(table)
    calls = count_calls(table, case_doc.get("physics"))
    lines = [f"# hmflow campaign `{campaign}`", "",
             f"Case **{case_doc['name']}** ({case_doc['source']}); {n} simulator calls: "
             f"{calls.text}.", ""]
    counts = table["status"].value_counts().to_dict() if n else {}
    doc: dict = {"campaign": campaign, "case": case_doc["name"], "calls": n,
                 "status_counts": counts, **calls.document(), "best": None,
                 "objective": choice.objective, "noise_refined": choice.noise,
                 "references": choice.references}
    if best is None:
        lines += ["No valid simulation: nothing can be called best.", ""]
        lines += calls_markdown(calls)
        return "\n".join(lines) + "\n", to_jsonable(doc)
    params = best["params"]
    lines += best_markdown(best, n, choice)
    doc["best"] = {"index": best["index"], "E": best["E"], "params": params,
                   "likelihood": best.get("likelihood"), "chosen_by": choice.objective,
                   "E_heldout": best.get("E_heldout"), "macro": best["metrics"].get("macro"),
                   "macro_informative": informative_macro(best["metrics"], info, "fit")}
    if truth:
        dist = truth_distance(case_doc, params, truth)
        doc["truth_distance"] = dist
        lines += ["", "### Distance to the known truth", "",
                  "| parameter | found | truth | error | error / range |", "|---|---|---|---|---|"]
        lines += [f"| {k} | {_fmt(d['found'])} | {_fmt(d['truth'])} | {_fmt(d['error'])} | "
                  f"{_fmt(d['error_of_range'], 3)} |" for k, d in dist.items()]
    if identifiability is not None:
        lines += [""] + identifiability_markdown(identifiability, case_doc.get("source", "CASE"),
                                                 truth)
        doc["identifiability"] = identifiability_document(identifiability, truth)
    wells = well_names(best["metrics"])
    lines += [""] + information_markdown(best["metrics"], info, "fit", wells)
    lines += [metrics_markdown(best["metrics"], "Fitted history", info, "fit")]
    doc["category_table"] = to_jsonable(category_table(best["metrics"]).to_dict(orient="records"))
    doc["well_table"] = to_jsonable(well_table(best["metrics"]).to_dict(orient="records"))
    doc["ratio_table"] = to_jsonable(ratio_table(best["metrics"]).to_dict(orient="records"))
    doc["information"] = to_jsonable(info.to_dict(orient="records"))
    if has_heldout(best):
        lines += heldout_markdown(best, case_doc, info, (choice or Choice()).references)
        doc["heldout_category_table"] = to_jsonable(
            category_table(best["heldout_metrics"]).to_dict(orient="records"))
        doc["heldout_macro_informative"] = informative_macro(best["heldout_metrics"], info,
                                                             "heldout")
    lines += calls_markdown(calls)
    if n:
        lines += convergence_markdown(table, choice)
        doc["time"] = {"sim_time_s_total": float(table["sim_time_s"].sum()),
                       "wall_time_s_total": float(table["wall_time_s"].sum())}
    return "\n".join(lines) + "\n", to_jsonable(doc)


def best_markdown(best: dict, calls: int, choice: Choice) -> list[str]:
    """The best case's heading, what chose it (:func:`choice_markdown`) and its parameters."""
    key = choice.objective if choice.objective in best else "E"
    lines = [f"## Best case: call {best['index'] + 1} of {calls} ({key} = "
             f"{_fmt(best[key], 6)})", ""]
    lines += choice_markdown(best, choice)
    lines += ["| parameter | value |", "|---|---|"]
    return lines + [f"| {k} | {_fmt(v)} |" for k, v in best["params"].items()]


def truth_distance(case_doc: dict, params: dict, truth: dict[str, float]) -> dict:
    """:func:`parameter_distance` under the case's parameter bounds."""
    bounds = {p["name"]: (p["low"], p["high"]) for p in case_doc["parameters"]}
    return parameter_distance(params, truth, bounds)


def has_heldout(best: dict | None) -> bool:
    """The best case was scored on a held-back history."""
    return bool(best and (best.get("heldout_metrics") or {}).get("categories"))


def heldout_markdown(best: dict, case_doc: dict, info: pd.DataFrame,
                     references: dict | None = None) -> list[str]:
    """The held-back history's section: its E beside the reference runs' (``references``:
    floor and centre, each with ``E_heldout``, when scored), which responses carry information
    there, the macro over them and the paper's three tables."""
    metrics = best["heldout_metrics"]
    end = case_doc.get("fit_history_end_days", case_doc.get("history_end_days"))
    beside = [f"{label} {_fmt(float(doc['E_heldout']), 6)}" for key, label in
              (("floor", "truth / deck values"), ("centre", "prior centre"))
              if (doc := (references or {}).get(key)) and doc.get("E_heldout") is not None]
    lines = ["## Held-back history", "",
             f"Held-back history (after day {end}): E = {_fmt(best.get('E_heldout'), 6)}"
             + (f" ({'; '.join(beside)})" if beside else "") + ". "
             "These data were measured but not fitted: how the best case does on them is the "
             "test of its prediction.", ""]
    lines += information_markdown(metrics, info, "heldout", well_names(metrics), level=3)
    return lines + [metrics_markdown(metrics, "Held-back history", info, "heldout")]


def convergence_markdown(table: pd.DataFrame, choice: Choice) -> list[str]:
    """The lowest E of any valid call (and the choosing objective's best) so far at a quarter,
    half, three quarters and all of the calls."""
    n = len(table)
    both = choice.objective != "E" and "best_objective_so_far" in table
    trace = table[["index", "best_E_so_far"] + (["best_objective_so_far"] if both else [])
                  ].dropna()
    marks = sorted({max(1, n // 4), max(1, n // 2), max(1, 3 * n // 4), n})
    lines = ["### Convergence", "", "| calls | lowest E so far (any valid call) |"
             + (f" best {choice.objective} so far (chooses) |" if both else ""),
             "|---|---|" + ("---|" if both else "")]
    for m in marks:
        sub = trace[trace["index"] < m]
        cells = [_fmt(sub[c].iloc[-1], 6) if len(sub) else "n/a" for c in trace.columns[1:]]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines + [""]


# ---------------------------------------------------------------- which responses carry information
INFORMATION_NOTE = (
    "A response carries no information about the model when it is the well's **rate "
    "control** (the simulator produces that rate by construction: every model scores C_match "
    "100 on it), when its observed series is **within its noise of zero** (a zero rate fits it "
    f"within the noise: no value beyond {Z_BEYOND_NOISE:g} sigma of zero; C_match = 100 / (1 + "
    "NMSE) of noise around zero is about 50 % for any model with the rate about right, the "
    "truth too) or when the noise estimate flags it **within the noise floor of zero** (see the "
    "noise section). Such a response is marked in the tables and grey in the heatmap, not "
    "scored as a match or a miss, and the macro scores below leave out a category none of "
    "whose wells carries information.")


def well_names(metrics: dict) -> list[str]:
    """The wells a metrics document scores, in natural order."""
    return sorted(metrics.get("wells") or {}, key=natural_key)


def information_markdown(metrics: dict, info: pd.DataFrame, period: str, wells: list[str],
                         level: int = 2) -> list[str]:
    """Which responses of ``period`` carry information (a well x category table: 'yes' or why
    not) and the macro scores over those that do, beside the paper's."""
    grid = information_grid(info, period, wells)
    lines = [f"{'#' * level} Which responses carry information"
             + (" (held-back history)" if period == "heldout" else ""), ""]
    if level == 2:
        lines += [INFORMATION_NOTE, ""]
    if len(grid.columns) > 1:
        lines += [paper_tables.markdown_table(grid), ""]
    return lines + [macro_text(metrics, info, period), ""]


def macro_text(metrics: dict, info: pd.DataFrame, period: str) -> str:
    """The macro scores over the responses that carry information, what they include and leave
    out, and the paper's macro over every primary category."""
    mine = informative_macro(metrics, info, period)
    paper = metrics.get("macro") or {}
    out = ", ".join(f"{c} ({why} at every well)" for c, why in mine["left_out"].items())
    return (f"Macro over the responses that carry information ({', '.join(mine['includes'])}"
            + (f"; left out: {out}" if out else "") + f"): NMSE {_fmt(mine['nmse'])}, "
            f"R\u00b2 {_fmt(mine['r2'])}, C_match {_fmt(mine['cmatch'], 2)} %. The paper's "
            f"macro over every primary category ({', '.join(macro_categories(metrics))}): "
            f"C_match {_fmt(paper.get('cmatch'), 2)} %.")


def marked_tables(metrics: dict, info: pd.DataFrame | None, period: str
                  ) -> dict[str, pd.DataFrame]:
    """The paper's three tables (:func:`hmcore.reporting.paper_tables.paper_tables`), the
    C_match of a well's response that carries no information followed by why ('100.00 (rate
    control)')."""
    tables = paper_tables.paper_tables(metrics)
    if info is None:
        return tables
    marks = uninformative(info, period)
    wells = tables["wells"].astype(object)
    for i, row in wells.iterrows():
        for cat in wells.columns[1:]:
            why = marks.get((row["well"], cat))
            wells.at[i, cat] = paper_tables.cell(cat, row[cat]) + (f" ({why})" if why else "")
    return {**tables, "wells": wells}
