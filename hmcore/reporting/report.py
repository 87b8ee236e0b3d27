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
from hmcore.reporting import paper_tables
from hmcore.scoring.metrics import category_table, ratio_table, well_table
from hmcore.scoring.noise_table import noise_markdown
from storage.jsonable import to_jsonable


def _fmt(v: Any, digits: int = 4) -> str:
    if isinstance(v, (float, np.floating)):
        return "n/a" if not math.isfinite(v) else f"{v:.{digits}g}" if abs(v) < 1e-3 else f"{v:.{digits}f}"
    return str(v)


def metrics_markdown(metrics: dict, title: str = "Match quality") -> str:
    """The paper's three tables (see :mod:`hmcore.reporting.paper_tables`)."""

    return paper_tables.markdown(paper_tables.paper_tables(metrics), title)


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
    noise = choice.noise or {}
    if noise.get("refinement"):
        lines += ["", f"The likelihood is under the noise refined {noise['refinement']} time(s) "
                  f"from the fit's residuals, last from call {noise['refined_from_call'] + 1}."]
    return lines + [""]


def build_report(campaign: str, case_doc: dict, table: pd.DataFrame | None, best: dict | None,
                 truth: dict[str, float] | None,
                 diagnosis: dict | None = None,
                 noise: pd.DataFrame | None = None,
                 choice: Choice | None = None) -> tuple[str, dict]:
    """Markdown report and its JSON twin from stored results (no simulator involved).

    ``table``: the consolidated evaluations (None: the campaign ran no calibration, e.g. a
    diagnosis alone); ``diagnosis``: the campaign's latest ``diagnosis.json``, appended as a
    section (its plots are linked by file name, stored beside the report); ``noise``: the
    noise the fit assumed (:func:`hmcore.scoring.noise_table.noise_summary`, stored with the
    campaign's case, or its latest refinement), a section of its own; ``choice``: what chose
    the best call (default: E, as campaigns did before the objective)."""
    choice = choice or Choice()
    if table is None:
        markdown = "\n".join([f"# hmflow campaign `{campaign}`", "",
                               f"Case **{case_doc['name']}** ({case_doc['source']}); no "
                               "calibration campaign was run under this name.", ""]) + "\n"
        doc: dict = {"campaign": campaign, "case": case_doc["name"], "calls": 0, "best": None}
    else:
        markdown, doc = _campaign_report(campaign, case_doc, table, best, truth, choice)
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
                     truth: dict[str, float] | None, choice: Choice) -> tuple[str, dict]:
    n = len(table)
    counts = table["status"].value_counts().to_dict() if n else {}
    lines = [f"# hmflow campaign `{campaign}`", "",
             f"Case **{case_doc['name']}** ({case_doc['source']}); {n} simulator calls: "
             + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) + ".", ""]
    doc: dict = {"campaign": campaign, "case": case_doc["name"], "calls": n,
                 "status_counts": counts, "best": None, "objective": choice.objective,
                 "noise_refined": choice.noise, "references": choice.references}
    fails = table[table["status"] == "FAIL"]
    if not fails.empty:
        reasons = fails["failure"].fillna("unknown").value_counts().to_dict()
        lines += [f"Failed calls by kind: {reasons}.", ""]
        doc["failure_reasons"] = reasons
    kinds: dict[str, int] = {}
    if "violation_kinds" in table:
        for cell in table["violation_kinds"].dropna():
            for kind in set(filter(None, str(cell).split(","))):  # a call counts once per check
                kinds[kind] = kinds.get(kind, 0) + 1
    if kinds:
        lines += [f"Physics checks broken (calls penalised by each; see hmcore.scoring.physics): {kinds}.",
                  ""]
        doc["violation_counts"] = kinds
    if best is None:
        lines += ["No valid simulation: nothing can be called best."]
        return "\n".join(lines) + "\n", to_jsonable(doc)
    params = best["params"]
    key = choice.objective if choice.objective in best else "E"
    lines += [f"## Best case: call {best['index'] + 1} of {n} ({key} = "
              f"{_fmt(best[key], 6)})", ""]
    lines += choice_markdown(best, choice)
    lines += ["| parameter | value |", "|---|---|"]
    lines += [f"| {k} | {_fmt(v)} |" for k, v in params.items()]
    doc["best"] = {"index": best["index"], "E": best["E"], "params": params,
                   "likelihood": best.get("likelihood"), "chosen_by": choice.objective,
                   "E_heldout": best.get("E_heldout"), "macro": best["metrics"].get("macro")}
    if truth:
        bounds = {p["name"]: (p["low"], p["high"]) for p in case_doc["parameters"]}
        dist = parameter_distance(params, truth, bounds)
        doc["truth_distance"] = dist
        lines += ["", "### Distance to the known truth", "",
                  "| parameter | found | truth | error | error / range |", "|---|---|---|---|---|"]
        lines += [f"| {k} | {_fmt(d['found'])} | {_fmt(d['truth'])} | {_fmt(d['error'])} | "
                  f"{_fmt(d['error_of_range'], 3)} |" for k, d in dist.items()]
    lines += ["", metrics_markdown(best["metrics"], "Fitted history")]
    cat = category_table(best["metrics"])
    wells = well_table(best["metrics"])
    doc["category_table"] = to_jsonable(cat.to_dict(orient="records"))
    doc["well_table"] = to_jsonable(wells.to_dict(orient="records"))
    doc["ratio_table"] = to_jsonable(ratio_table(best["metrics"]).to_dict(orient="records"))
    if best.get("heldout_metrics") and best["heldout_metrics"].get("categories"):
        lines += [f"Held-back history (after day {case_doc.get('history_end_days')}): "
                  f"E = {_fmt(best.get('E_heldout'), 6)}", "",
                  metrics_markdown(best["heldout_metrics"], "Held-back history")]
        doc["heldout_category_table"] = to_jsonable(
            category_table(best["heldout_metrics"]).to_dict(orient="records"))
    if n:
        both = choice.objective != "E" and "best_objective_so_far" in table
        trace = table[["index", "best_E_so_far"]
                      + (["best_objective_so_far"] if both else [])].dropna()
        marks = sorted({max(1, n // 4), max(1, n // 2), max(1, 3 * n // 4), n})
        lines += ["### Convergence", "", "| calls | best E so far |"
                  + (f" best {choice.objective} so far (chooses) |" if both else ""),
                  "|---|---|" + ("---|" if both else "")]
        for m in marks:
            sub = trace[trace["index"] < m]
            cells = [_fmt(sub[c].iloc[-1], 6) if len(sub) else "n/a" for c in trace.columns[1:]]
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        doc["time"] = {"sim_time_s_total": float(table["sim_time_s"].sum()),
                       "wall_time_s_total": float(table["wall_time_s"].sum())}
    return "\n".join(lines) + "\n", to_jsonable(doc)
