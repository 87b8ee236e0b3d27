"""Names the tasks give in the Prefect UI: artifact keys from a campaign name, and task-run
names with the call number."""

from __future__ import annotations

import re

ARTIFACT_KEY_CHARS = "abcdefghijklmnopqrstuvwxyz0123456789-"


def artifact_key(name: str, suffix: str) -> str:
    """A Prefect artifact key (lowercase letters, digits, dashes) from a campaign name."""
    base = "".join(ch if ch in ARTIFACT_KEY_CHARS else "-" for ch in name.lower())
    return f"{base}-{suffix}"


ENSEMBLE_PHASE = re.compile(r"i\d{2,}")
REFERENCE_PHASES = ("floor", "centre")  # the reference runs (tasks.reference), outside the budget


def simulate_run_name() -> str:
    """``sim-017`` for call 17 (calls are numbered from 1); ``ref-floor`` and ``ref-centre``
    for the two reference runs, which are no call of the budget; ``i01-m0003`` for member 3
    of an ensemble's iteration 1."""
    from prefect.runtime import task_run

    job = task_run.parameters.get("job")
    if job is None:
        return "sim"
    if job.phase in REFERENCE_PHASES:
        return f"ref-{job.phase}"
    if ENSEMBLE_PHASE.fullmatch(job.phase):  # a member of an ensemble (tasks.ensemble)
        return f"{job.phase}-m{job.index:04d}"
    return f"sim-{job.index + 1:03d}"
