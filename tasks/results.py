"""Consolidation, best-case archive and report tasks (versioned artifacts; no simulator)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd
from prefect import task
from prefect.artifacts import create_link_artifact, create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE

from hmcore.calibration.loop import best_record
from hmcore.calibration.objective import Objective
from hmcore.diagnosis.report import markdown_report
from hmcore.fields.members import INCLUDE_NAME
from hmcore.model.case import default_history_end
from hmcore.reporting.benchmark import case_truth
from hmcore.reporting.html import ReportInputs, render
from hmcore.reporting.identifiability import load_identifiability
from hmcore.reporting.paper_tables import paper_tables
from hmcore.reporting.report import Choice, build_report, to_jsonable
from hmcore.reporting.results import results_table
from hmcore.scoring.information import information_table
from hmcore.scoring.noise_table import flagged_series
from hmcore.scoring.observations import ObservationSet
from storage import ArtifactStore, ArtifactVersion, EvaluationJournal, code_version, sha256_json
from tasks.curves import collect
from tasks.naming import artifact_key
from tasks.noise import latest_noise
from tasks.reference import CENTRE, FLOOR, reference_name

SUMMARY_SUFFIXES = (".SMSPEC", ".UNSMRY", ".DATA", ".LOG", ".PRT", ".INIT", ".EGRID")


@task(name="consolidate-results", cache_policy=NO_CACHE)
def consolidate(store_root: str, campaign: str, parameter_names: list[str],
                objective: Objective | None = None,
                references: dict[int, dict] | None = None) -> ArtifactVersion:
    """Every journaled evaluation -> ``results/vN/evaluations.parquet`` (+ records JSON).

    With the campaign's final ``objective`` every record gains ``likelihood`` (under the
    noise the campaign ended with; NaN without simulated values) and ``records.json`` says
    which objective chooses (``objective``); ``references`` (the reference runs' records by
    index) are scored the same way (``references``: floor and centre, E and likelihood)."""
    store = ArtifactStore(store_root)
    rows = EvaluationJournal(store, campaign).rows()
    name = objective.name if objective is not None else "E"
    if objective is not None and objective.observations is not None:
        rows = [{**r, "likelihood": objective.likelihood(r)} for r in rows]
    scored_refs = {label: {"E": rec.get("E"), "E_heldout": rec.get("E_heldout"), "likelihood": (
        objective.likelihood(rec) if objective is not None and objective.observations
        is not None else None)} for label, rec in (
        ("floor", (references or {}).get(FLOOR)), ("centre", (references or {}).get(CENTRE)))
        if rec is not None}
    table = results_table(rows, parameter_names, name)
    noise = objective.describe() if objective is not None else None
    return store.put_files(campaign, "results", {"journal": sha256_json(rows),
                                                 "parameters": parameter_names,
                                                 "objective": name, "noise": noise},
                           {"evaluations.parquet": table,
                            "records.json": {"records": rows, "objective": name,
                                             "noise": noise, "references": scored_refs}},
                           code_version())


@task(name="archive-best-case", cache_policy=NO_CACHE)
def archive_best(store_root: str, campaign: str, results: ArtifactVersion) -> ArtifactVersion | None:
    """Copy the best valid run by the campaign's objective (deck, summary files, parameters,
    metrics; a latent campaign's fields, :data:`~hmcore.fields.members.INCLUDE_NAME`, included
    by the copied deck from beside it) into ``best/vN``."""
    store = ArtifactStore(store_root)
    doc = results.read_json("records.json")
    records = doc["records"]
    objective = doc.get("objective", "E")
    best = best_record(records, objective)
    if best is None:
        return None
    run_dir = Path(best["run_dir"])

    def write(directory: Path) -> None:
        fields = run_dir / INCLUDE_NAME  # a latent or member run's fields, included by the deck
        for f in sorted(run_dir.iterdir()):
            if f.is_file() and (f.suffix.upper() in SUMMARY_SUFFIXES or f.name == "simulator.log"
                                or f == fields):
                shutil.copy2(f, directory / f.name)
        for deck in directory.glob("*.DATA"):  # the archive's own copy, not the run dir's
            if fields.is_file():
                deck.write_text(deck.read_text(errors="replace").replace(
                    f"'{fields.resolve()}'", f"'{INCLUDE_NAME}'"))
        (directory / "params.json").write_text(json.dumps(best["params"], indent=2))
        kept = {k: v for k, v in best.items() if k != "simulated"}
        (directory / "metrics.json").write_text(json.dumps(to_jsonable(
            {**kept, "objective": objective}), indent=2))

    return store.put(campaign, "best", {"results": results.ref(), "index": best["index"],
                                        "objective": objective}, write, code_version())


@task(name="build-report", cache_policy=NO_CACHE)
def report(store_root: str, campaign: str, publish_prefect_artifacts: bool = True) -> ArtifactVersion:
    """Rebuild the report from stored artifacts only (zero simulator calls): the campaign's
    results and best case, and its latest diagnosis (``diagnosis-report``) when it has one, its
    plots copied beside ``report.md``. A report of the same inputs and code is the stored one:
    its Prefect artifacts are published again and no figure is drawn."""
    store = ArtifactStore(store_root)
    store.require_campaign(campaign)  # gone: a storage fault (removed while the flow ran)
    results = store.latest(campaign, "results")
    case = store.latest(campaign, "case")
    diagnosis = store.latest(campaign, "diagnosis-report")
    if case is None or (results is None and diagnosis is None):
        raise FileNotFoundError(f"campaign '{campaign}' in {store_root} has no stored results "
                                "and no diagnosis; run the campaign first (hmflow run, or "
                                "hmflow diagnose)")
    best = store.latest(campaign, "best") if results is not None else None
    best_doc = best.read_json("metrics.json") if best else None
    refined = latest_noise(store, campaign)
    inputs = {"results": results.ref() if results is not None else None, "case": case.ref(),
              "noise": refined.ref() if refined is not None else None,
              "report_version": REPORT_VERSION,
              "best": best.ref() if best else None}
    if diagnosis is not None:
        inputs["diagnosis"] = diagnosis.ref()
    curves = store.latest(campaign, "curves")
    if curves is None and results is not None:  # a campaign from before curves were stored:
        curves = collect(store_root, campaign, campaign_reference(store, campaign))  # run dirs
    if curves is not None:
        inputs["curves"] = curves.ref()
    stored = store.reusable(campaign, "report", inputs, code_version())
    if stored is not None:  # the store would keep this version: draw nothing
        if publish_prefect_artifacts:
            publish(campaign, stored.file("report.md").read_text(encoding="utf-8"), best_doc,
                    stored.file("report.html"))
        return stored

    case_doc = case.read_json("case.json")
    table = results.read_parquet("evaluations.parquet") if results is not None else None
    diagnosis_doc = diagnosis.read_json("diagnosis.json") if diagnosis is not None else None
    truth = _truth_for(case_doc)
    noise_from = refined if refined is not None else case
    noise = (noise_from.read_parquet("noise.parquet") if "noise.parquet" in noise_from.files
             else None)
    scores = results.read_json("records.json") if results is not None else {}
    choice = Choice(scores.get("objective", "E"), scores.get("noise"),
                    _with_heldout(store, campaign, scores.get("references")))
    plots = {name: diagnosis.file(name).read_bytes()
             for name in (diagnosis_doc or {}).get("plots", []) if name in diagnosis.files}
    identifiability = load_identifiability(store, campaign) if results is not None else None
    page = report_inputs(store, campaign, case_doc, table, best_doc, truth, curves,
                         diagnosis_doc, _diagnosis_markdown(diagnosis_doc),
                         {n: b for n, b in plots.items() if n.endswith(".png")}, noise, choice,
                         identifiability)
    markdown, doc = build_report(campaign, case_doc, table, best_doc, truth, diagnosis_doc,
                                 noise, choice, page.information, identifiability)
    files: dict = {"report.md": markdown, "report.json": doc, **plots}
    html, pngs = render(page)
    files["report.html"] = html
    files.update({n: b for n, b in pngs.items() if not n.startswith("diagnosis__")})
    version = store.put_files(campaign, "report", inputs, files, code_version())
    if publish_prefect_artifacts:
        publish(campaign, markdown, best_doc, version.file("report.html"))
    return version


REPORT_VERSION = 4  # 2: report.html; 3: held-back history, information, calls in words;
# 4: identifiability at the best call


def campaign_reference(store: ArtifactStore, campaign: str) -> str:
    """The campaign holding ``campaign``'s reference runs (stored in its campaign.json; by
    default CAMPAIGN-reference)."""
    stored = (store.settings(campaign) or {}).get("reference")
    return stored or reference_name(campaign)


def _diagnosis_markdown(diagnosis_doc: dict | None) -> str | None:
    if diagnosis_doc is None:
        return None

    return markdown_report(diagnosis_doc, level=2)


def _with_heldout(store: ArtifactStore, campaign: str, references: dict | None) -> dict | None:
    """The scored reference runs with each one's held-back E from its record (results
    consolidated before they kept it have none)."""
    if not references:
        return references
    reference = campaign_reference(store, campaign)
    if not store.has_campaign(reference):
        return references
    rows = {r["index"]: r for r in EvaluationJournal(store, reference).rows()}
    index = {"floor": FLOOR, "centre": CENTRE}
    return {k: {**v, "E_heldout": v.get("E_heldout", (rows.get(index.get(k)) or {}).get(
        "E_heldout"))} for k, v in references.items()}


def report_inputs(store: ArtifactStore, campaign: str, case_doc: dict, table, best_doc,
                  truth, curves: ArtifactVersion | None, diagnosis_doc: dict | None,
                  diagnosis_markdown: str | None, diagnosis_pngs: dict,
                  noise: pd.DataFrame | None = None, choice: Choice | None = None,
                  identifiability=None) -> ReportInputs:
    """Load what report.html is drawn from (stored artifacts only); ``noise``: the noise the
    fit assumed (its summary table), ``choice``: what chose the best call,
    ``identifiability``: what the data pin down there
    (:func:`hmcore.reporting.identifiability.load_identifiability`)."""
    case = store.latest(campaign, "case")
    observed = case.read_parquet("observed.parquet") if "observed.parquet" in case.files \
        else None
    obs = None
    if "observations.parquet" in case.files:  # the rows the fit weighed, as it weighed them
        obs_rows = case.read_parquet("observations.parquet")
        history_end = case_doc["fit_history_end_days"]
    elif observed is not None:  # a case stored before the weighed rows were
        end = case_doc.get("history_end_days")
        if end is None:  # ObservationSet.from_case's split
            end = default_history_end(observed.days.min(), observed.days.max())
        obs = ObservationSet.from_observed(observed, float(end),
                                           float(case_doc.get("time_tolerance_days", 30.0)))
        obs_rows, history_end = obs.rows, obs.history_end_days
    else:
        obs_rows, history_end = None, case_doc.get("history_end_days")
    forecast_doc = curves.read_json("forecast.json") if curves is not None else None
    refs = {}
    reference = (forecast_doc or {}).get("reference") or campaign_reference(store, campaign)
    if store.has_campaign(reference):
        rows = {r["index"]: r for r in EvaluationJournal(store, reference).rows()}
        refs = {"floor": (rows.get(FLOOR) or {}).get("E"),
                "centre": (rows.get(CENTRE) or {}).get("E")}
    agent = (store.settings(campaign) or {}).get("agent", "")
    return ReportInputs(
        campaign=campaign, case_doc=case_doc, agent=agent,
        table=table if table is not None else pd.DataFrame(columns=["index", "status", "E"]),
        best=best_doc, observed=obs_rows, history_end=history_end,
        curves=curves.read_parquet("curves.parquet") if curves is not None else None,
        forecast=curves.read_parquet("forecast.parquet") if curves is not None else None,
        forecast_doc=forecast_doc, references={k: v for k, v in refs.items() if v is not None},
        truth=truth, diagnosis_markdown=diagnosis_markdown,
        diagnosis_figures=diagnosis_pngs, code=code_version(), choice=choice, noise=noise,
        information=_information(observed, obs_rows, noise, history_end),
        identifiability=identifiability)


def _information(observed: pd.DataFrame | None, rows: pd.DataFrame | None,
                 noise: pd.DataFrame | None, history_end: float | None) -> pd.DataFrame | None:
    """Which responses carry information (:func:`hmcore.scoring.information.information_table`)
    from the weighed rows, the history's controlled rows and the noise summary's flags."""
    if rows is None:
        return None
    controlled = None
    if observed is not None and "controlled" in observed:
        controlled = observed[observed.controlled.astype(bool)]
    return information_table(rows, controlled, flagged_series(noise, rows), history_end)


def publish(campaign: str, markdown: str, best_doc: dict | None, report_html: Path) -> None:
    """The report as Prefect artifacts: the Markdown, a link to the stored HTML report, and the
    paper's three tables of the best case in the paper's rounding."""
    create_markdown_artifact(markdown, key=artifact_key(campaign, "report"),
                             description=f"hmflow report {campaign}")
    create_link_artifact(report_html.resolve().as_uri(), link_text=f"{campaign}: report.html",
                         key=artifact_key(campaign, "report-file"),
                         description="the HTML report with every well's curves (versioned, "
                                     "rebuilt by hmflow report; open it on the machine that "
                                     "holds the store)")
    if not best_doc:
        return
    heads = {"categories": "match by category (best case)",
             "wells": "C_match (%) per well and category (best case)",
             "ratios": "GOR and water cut per well: records used, left out and why (best case)"}
    for name, df in paper_tables(best_doc["metrics"]).items():
        create_table_artifact(to_jsonable(df.to_dict(orient="records")),
                              key=artifact_key(campaign, name), description=heads[name])


def _truth_for(case_doc: dict) -> dict | None:
    """Known true parameters: ``truth.json`` beside the case file (the synthetic case) or the
    ``truth`` of a ``hmflow hide`` case with nothing hidden (see hmcore.reporting.benchmark.case_truth)."""
    return case_truth(Path(case_doc["source"]))
