"""Consolidation, best-case archive and report tasks (versioned artifacts; no simulator)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from prefect import task
from prefect.artifacts import (create_link_artifact, create_markdown_artifact,
                               create_table_artifact)
from prefect.cache_policies import NO_CACHE

from tasks.naming import artifact_key
from hmcore.calibration import best_record
from hmcore.report import build_report, to_jsonable
from hmcore.results import results_table
from storage import ArtifactStore, ArtifactVersion, EvaluationJournal, code_version, sha256_json

SUMMARY_SUFFIXES = (".SMSPEC", ".UNSMRY", ".DATA", ".LOG", ".PRT", ".INIT", ".EGRID")


@task(name="consolidate-results", cache_policy=NO_CACHE)
def consolidate(store_root: str, campaign: str, parameter_names: list[str]) -> ArtifactVersion:
    """Every journaled evaluation -> ``results/vN/evaluations.parquet`` (+ records JSON)."""
    store = ArtifactStore(store_root)
    rows = EvaluationJournal(store, campaign).rows()
    table = results_table(rows, parameter_names)
    return store.put_files(campaign, "results", {"journal": sha256_json(rows),
                                                 "parameters": parameter_names},
                           {"evaluations.parquet": table, "records.json": {"records": rows}},
                           code_version())


@task(name="archive-best-case", cache_policy=NO_CACHE)
def archive_best(store_root: str, campaign: str, results: ArtifactVersion) -> ArtifactVersion | None:
    """Copy the best valid run (deck, summary files, parameters, metrics) into ``best/vN``."""
    store = ArtifactStore(store_root)
    records = results.read_json("records.json")["records"]
    best = best_record(records)
    if best is None:
        return None
    run_dir = Path(best["run_dir"])

    def write(directory: Path) -> None:
        for f in sorted(run_dir.iterdir()):
            if f.is_file() and (f.suffix.upper() in SUMMARY_SUFFIXES or f.name == "simulator.log"):
                shutil.copy2(f, directory / f.name)
        (directory / "params.json").write_text(json.dumps(best["params"], indent=2))
        (directory / "metrics.json").write_text(json.dumps(to_jsonable(best), indent=2))

    return store.put(campaign, "best", {"results": results.ref(), "index": best["index"]}, write,
                     code_version())


@task(name="build-report", cache_policy=NO_CACHE)
def report(store_root: str, campaign: str, publish_prefect_artifacts: bool = True) -> ArtifactVersion:
    """Rebuild the report from stored artifacts only (zero simulator calls): the campaign's
    results and best case, and its latest diagnosis (``diagnosis-report``) when it has one, its
    plots copied beside ``report.md``."""
    store = ArtifactStore(store_root)
    results = store.latest(campaign, "results")
    case = store.latest(campaign, "case")
    diagnosis = store.latest(campaign, "diagnosis-report")
    if case is None or (results is None and diagnosis is None):
        raise FileNotFoundError(f"campaign '{campaign}' in {store_root} has no stored results "
                                "and no diagnosis; run the campaign first (hmflow run, or "
                                "hmflow diagnose)")
    best = store.latest(campaign, "best") if results is not None else None
    case_doc = case.read_json("case.json")
    table = results.read_parquet("evaluations.parquet") if results is not None else None
    best_doc = best.read_json("metrics.json") if best else None
    diagnosis_doc = diagnosis.read_json("diagnosis.json") if diagnosis is not None else None
    truth = _truth_for(case_doc)
    markdown, doc = build_report(campaign, case_doc, table, best_doc, truth, diagnosis_doc)
    inputs = {"results": results.ref() if results is not None else None, "case": case.ref(),
              "best": best.ref() if best else None}
    if diagnosis is not None:
        inputs["diagnosis"] = diagnosis.ref()
    files: dict = {"report.md": markdown, "report.json": doc}
    for name in (diagnosis_doc or {}).get("plots", []):
        if name in diagnosis.files:
            files[name] = diagnosis.file(name).read_bytes()
    version = store.put_files(campaign, "report", inputs, files, code_version())
    if publish_prefect_artifacts:
        publish(campaign, markdown, best_doc, version.file("report.md"))
    return version


def publish(campaign: str, markdown: str, best_doc: dict | None, report_md: Path) -> None:
    """The report as Prefect artifacts: the Markdown, a link to the stored file, and the paper's
    three tables of the best case in the paper's rounding."""
    from hmcore.paper_tables import paper_tables

    create_markdown_artifact(markdown, key=artifact_key(campaign, "report"),
                             description=f"hmflow report {campaign}")
    create_link_artifact(report_md.resolve().as_uri(), link_text=f"{campaign}: report.md",
                         key=artifact_key(campaign, "report-file"),
                         description="the stored report (versioned, rebuilt by hmflow report)")
    if not best_doc:
        return
    heads = {"categories": "match by category (best case)",
             "wells": "C_match (%) per well and category (best case)",
             "ratios": "GOR and water cut per well: records used, left out and why (best case)"}
    for name, df in paper_tables(best_doc["metrics"]).items():
        create_table_artifact(to_jsonable(df.to_dict(orient="records")),
                              key=artifact_key(campaign, name), description=heads[name])


def _truth_for(case_doc: dict) -> dict | None:
    """Known true parameters (synthetic cases ship truth.json beside case.toml)."""
    path = Path(case_doc["source"]).parent / "truth.json"
    if path.is_file():
        return json.loads(path.read_text()).get("parameters")
    return None
