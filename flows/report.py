"""Report-only rerun: rebuild a campaign's report from stored artifacts (no simulator)."""

from __future__ import annotations

from pathlib import Path

from prefect import flow

from tasks.results import report


@flow(name="hmflow-report")
def report_flow(storage: str, campaign: str) -> dict:
    version = report(str(Path(storage).resolve()), campaign)
    return {"report": version.ref(), "report_path": str(version.file("report.md")),
            "reused": version.reused}
