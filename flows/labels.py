"""How hmflow's flow runs read in the Prefect UI: names from the campaign, tags (case, agent,
seed) and a progress artifact with the lowest E so far (task-run names: :mod:`tasks.naming`)."""

from __future__ import annotations

import math
from datetime import datetime, timezone

from hmcore.calibration.registry import DEFAULT_AGENT, default_campaign_name
from hmcore.cases import case_name
from tasks.naming import artifact_key


def _stamp() -> str:
    return datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")


def campaign_run_name() -> str:
    """``<campaign>-<UTC date and time>``; the campaign is the given one or its default name."""
    from prefect.runtime import flow_run

    p = flow_run.parameters
    try:
        name = p.get("campaign") or default_campaign_name(case_name(p.get("case", "synthetic")),
                                                          p.get("agent", DEFAULT_AGENT), p.get("seed", 0))
    except (OSError, ValueError):  # a bad case path: the flow itself reports it
        name = "campaign"
    return f"{name}-{_stamp()}"


def named_run(key: str, default: str, suffix: str = ""):
    """A flow-run name function: ``<parameter key's value or default><suffix>-<UTC time>``."""
    def name() -> str:
        from prefect.runtime import flow_run

        return f"{flow_run.parameters.get(key) or default}{suffix}-{_stamp()}"

    return name


def tag_flow_run(*tags: str) -> None:
    """Add ``tags`` to the current flow run (its list in the UI and its filters)."""
    from prefect.client.orchestration import get_client
    from prefect.runtime import flow_run

    run_id = flow_run.id
    if run_id is None:
        return
    with get_client(sync_client=True) as client:
        current = client.read_flow_run(run_id)
        client.update_flow_run(run_id, tags=sorted(set(current.tags) | set(tags)))


class Progress:
    """A progress artifact of a campaign: calls done of the budget, and the lowest E of a
    valid call so far in its description (the campaign's objective, which chooses the best
    call, is known only at the end: its noise is refined on the way), updated after every
    batch of simulator calls."""

    def __init__(self, campaign: str, budget: int):
        from prefect.artifacts import create_progress_artifact

        self.budget = budget
        self.best = math.inf
        self.done = 0
        self.id = create_progress_artifact(0.0, key=artifact_key(campaign, "progress"),
                                           description=f"{campaign}: 0/{budget} calls")
        self.campaign = campaign

    def update(self, records: list[dict]) -> None:
        from prefect.artifacts import update_progress_artifact

        self.done += len(records)
        for r in records:
            if r.get("status") == "COMPLETE" and r.get("E") is not None:
                self.best = min(self.best, float(r["E"]))
        best = (f"lowest E so far {self.best:.5g}" if math.isfinite(self.best)
                else "no valid call yet")
        update_progress_artifact(self.id, min(100.0, 100.0 * self.done / self.budget),
                                 description=f"{self.campaign}: {self.done}/{self.budget} calls, "
                                             f"{best}")

