"""Names the tasks give in the Prefect UI: artifact keys from a campaign name, and task-run
names with the call number."""

from __future__ import annotations

ARTIFACT_KEY_CHARS = "abcdefghijklmnopqrstuvwxyz0123456789-"


def artifact_key(name: str, suffix: str) -> str:
    """A Prefect artifact key (lowercase letters, digits, dashes) from a campaign name."""
    base = "".join(ch if ch in ARTIFACT_KEY_CHARS else "-" for ch in name.lower())
    return f"{base}-{suffix}"


def simulate_run_name() -> str:
    """``sim-017`` for call 17 (calls are numbered from 1)."""
    from prefect.runtime import task_run

    job = task_run.parameters.get("job")
    return f"sim-{job.index + 1:03d}" if job is not None else "sim"
