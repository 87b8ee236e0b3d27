"""The report of an ensemble run as a versioned artifact (``report/vN``: report.md,
report.html, report.json and the PNG figures), from stored artifacts only (zero simulator
calls): the last step of :func:`flows.ensemble.ensemble_flow`, and what ``hmflow report``
rebuilds for an ensemble run. The domain is :mod:`hmcore.reporting.ensemble`; this reads the
store (layout: :mod:`storage.ensemble`) and writes the artifact."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from prefect import task
from prefect.artifacts import create_link_artifact, create_markdown_artifact
from prefect.cache_policies import NO_CACHE

from hmcore.fields.layout import Layout
from hmcore.fields.members import ensemble_matrix
from hmcore.fields.spec import FieldSpec
from hmcore.ordering import natural_key
from hmcore.reporting.ensemble import REPORT_VERSION, EnsembleReportInputs, build
from hmcore.reporting.ensemble_truth import read_truth
from hmcore.simulation.curves import FIELD
from storage import ArtifactStore, ArtifactVersion, code_version, to_jsonable
from storage.ensemble import (
    CURVES_FILE,
    ENSEMBLE_DOC,
    ENSEMBLE_FILE,
    FORECAST_STEP,
    GRID_FILE,
    MISFIT_FILE,
    REPORT_STEP,
    ensemble_step,
)
from tasks.naming import artifact_key


class MissingReportInputs(FileNotFoundError):
    """The run lacks what the report is drawn from (the one line says what to do)."""


@task(name="ensemble-report", cache_policy=NO_CACHE)
def ensemble_report(store_root: str, campaign: str,
                    publish_prefect_artifacts: bool = True) -> ArtifactVersion:
    """Build the report of ensemble run ``campaign``, or reuse the stored one (nothing drawn)
    when nothing it reads changed; publish it as Prefect artifacts (the Markdown and a link
    to the HTML)."""
    store = ArtifactStore(store_root)
    settings = store.settings(campaign) or {}
    forecast = store.latest(campaign, FORECAST_STEP)
    case = store.latest(campaign, "case")
    if settings.get("kind") != "ensemble" or forecast is None or case is None:
        raise MissingReportInputs(f"'{campaign}' in {store_root} has no finished ensemble run "
                                  "(no stored forecast); run hmflow ensemble first")
    missing = [f for f in (CURVES_FILE, MISFIT_FILE) if f not in forecast.files]
    prior = store.latest(campaign, ensemble_step(0))
    if missing or GRID_FILE not in prior.files:
        raise MissingReportInputs(
            f"ensemble run '{campaign}' was stored before hmflow kept what its report draws "
            f"(the members' curves and misfits, the grid); run the same hmflow ensemble "
            f"command again: it simulates nothing and stores them")
    iterations = len(forecast.read_json("summary.json")["iterations"]) - 1
    posterior = store.latest(campaign, ensemble_step(iterations))
    inputs = load_inputs(store, campaign, case, prior, posterior, forecast, settings)
    refs = {"case": case.ref(), "prior": prior.ref(), "posterior": posterior.ref(),
            "forecast": forecast.ref(), "report_version": REPORT_VERSION,
            "truth": inputs.truth.digest() if inputs.truth is not None else None}

    def write(directory: Path) -> None:  # drawn only when no stored version has these inputs
        report = build(inputs)
        (directory / "report.md").write_text(report.markdown, encoding="utf-8")
        (directory / "report.html").write_text(report.html, encoding="utf-8")
        (directory / "report.json").write_text(json.dumps(
            to_jsonable(report.doc), indent=2, sort_keys=True, allow_nan=False) + "\n",
            encoding="utf-8")
        for name, data in report.figures.items():
            (directory / name).write_bytes(data)

    version = store.put(campaign, REPORT_STEP, refs, write, code_version())
    if publish_prefect_artifacts:
        create_markdown_artifact(version.file("report.md").read_text(encoding="utf-8"),
                                 key=artifact_key(campaign, "report"),
                                 description=f"hmflow ensemble report {campaign}")
        create_link_artifact(version.file("report.html").resolve().as_uri(),
                             link_text=f"{campaign}: report.html",
                             key=artifact_key(campaign, "report-file"),
                             description="the ensemble's HTML report (versioned; rebuilt by "
                                         "hmflow report)")
    return version


def load_inputs(store: ArtifactStore, campaign: str, case: ArtifactVersion,
                prior: ArtifactVersion, posterior: ArtifactVersion, forecast: ArtifactVersion,
                settings: dict) -> EnsembleReportInputs:
    """Read what the report is drawn from: the case as stored, the prior and the posterior
    ensembles with the grid, the forecast step's tables, and the case's truth when known."""
    case_doc = case.read_json("case.json")
    doc = prior.read_json(ENSEMBLE_DOC)
    layout = Layout(tuple(doc["fields"]), tuple(doc["scalars"]), int(doc["n_active"]))
    fields = tuple(FieldSpec.model_validate(f) for f in settings["fields"])
    dims = tuple(int(d) for d in doc["dims"])
    active = prior.read_parquet(GRID_FILE)["active"].to_numpy(np.int64)
    ensembles = {}
    for name, version in (("prior", prior), ("posterior", posterior)):
        X = ensemble_matrix(version.read_parquet(ENSEMBLE_FILE), layout)
        ensembles[name], _ = layout.split(X)
    wells = tuple(sorted((w for w in case_doc["wells"] if w != FIELD), key=natural_key))
    return EnsembleReportInputs(
        campaign=campaign, case_name=case_doc["name"], case_source=case_doc["source"],
        fields=fields, dims=dims, active=active, prior=ensembles["prior"],
        posterior=ensembles["posterior"], observed=case.read_parquet("observations.parquet"),
        history_end=case_doc.get("fit_history_end_days"),
        curves=forecast.read_parquet(CURVES_FILE), misfit=forecast.read_parquet(MISFIT_FILE),
        forecast=forecast.read_parquet("forecast.parquet"),
        summary=forecast.read_json("summary.json"), wells=wells,
        weights=tuple(settings.get("ensemble", {}).get("weights", ())),
        truth=read_truth(case_doc["source"], fields, dims, active, wells),
        code=code_version())
