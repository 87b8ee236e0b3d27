"""Report-only rerun: rebuild a campaign's (or an ensemble run's) report from stored
artifacts (no simulator)."""

from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.labels import named_run
from storage import ArtifactStore
from tasks.ensemble_report import ensemble_report
from tasks.results import report


@flow(name="hmflow-report", flow_run_name=named_run("campaign", "campaign", "-report"))
def report_flow(storage: str, campaign: str) -> dict:
    """Rebuild the report of ``campaign`` in ``storage``: an ensemble run's
    (:func:`tasks.ensemble_report.ensemble_report`) when its name is bound to one, else a
    calibration campaign's (:func:`tasks.results.report`)."""
    root = str(Path(storage).resolve())
    kind = (ArtifactStore(root).settings(campaign) or {}).get("kind")
    version = (ensemble_report if kind == "ensemble" else report)(root, campaign)
    return {"report": version.ref(), "report_path": str(version.file("report.md")),
            "report_html": str(version.file("report.html")),
            "reused": version.reused, "kind": kind or "campaign"}
