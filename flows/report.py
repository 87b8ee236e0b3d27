"""Report-only rerun: rebuild a campaign's report from stored artifacts (no simulator)."""

from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.labels import named_run
from tasks.results import report


@flow(name="hmflow-report", flow_run_name=named_run("campaign", "campaign", "-report"))
def report_flow(storage: str, campaign: str) -> dict:
    version = report(str(Path(storage).resolve()), campaign)
    return {"report": version.ref(), "report_path": str(version.file("report.md")),
            "report_html": str(version.file("report.html")),
            "reused": version.reused}
