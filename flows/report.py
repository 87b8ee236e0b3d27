"""Report-only rerun: rebuild a campaign's (or an ensemble run's) report from stored
artifacts (no simulator)."""

from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.labels import named_run
from storage import ArtifactStore
from tasks.curves import collect_curves, stale
from tasks.ensemble_report import ensemble_report
from tasks.results import report


@flow(name="hmflow-report", flow_run_name=named_run("campaign", "campaign", "-report"))
def report_flow(storage: str, campaign: str) -> dict:
    """Rebuild the report of ``campaign`` in ``storage``: an ensemble run's
    (:func:`tasks.ensemble_report.ensemble_report`) when its name is bound to one, else a
    calibration campaign's (:func:`tasks.results.report`), its curves collected again first
    from the run directories when they were drawn for another best call
    (:func:`tasks.curves.stale`)."""
    root = str(Path(storage).resolve())
    settings = ArtifactStore(root).settings(campaign) or {}
    kind = settings.get("kind")
    if kind != "ensemble" and stale(root, campaign):  # drawn for another best call
        collect_curves(root, campaign, settings.get("reference"))
    version = (ensemble_report if kind == "ensemble" else report)(root, campaign)
    return {"report": version.ref(), "report_path": str(version.file("report.md")),
            "report_html": str(version.file("report.html")),
            "reused": version.reused, "kind": kind or "campaign"}
