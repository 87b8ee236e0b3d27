"""The two reference runs a campaign and a benchmark are judged against, in their own journal:
call 0, the truth's values where the truth is known, else the deck's own values (the floor of
a benchmark, the "before" of a report); call 1, the box's centre (the prior centre, action 0).
They are simulator calls outside every budget; a campaign inside a benchmark shares the
benchmark's, so they run once per case and benchmark."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from hmcore.calibration.calls import Job
from hmcore.model.case import Case
from hmcore.model.deck_values import base_values
from hmcore.reporting import benchmark
from hmcore.scoring.evaluation import SCORING_VERSION
from storage import ArtifactStore, ArtifactVersion, EvaluationJournal
from tasks.simulate import simulate, simulate_parameters

REFERENCE_AGENT = "reference"
FLOOR, CENTRE = 0, 1


def reference_name(campaign: str) -> str:
    return f"{campaign}-reference"


def reference_jobs(case: Case, floor: Mapping[str, float] | None = None) -> list[Job]:
    """Call 0: the truth's values (known truth) or the deck's own, ``floor`` overriding them
    (the latent coefficients of the deck's fields); call 1: the box's centre."""
    truth = {**(benchmark.case_truth(case.source) or base_values(case.info, case.space)),
             **(floor or {})}
    truth = {n: float(truth[n]) for n in case.space.names}
    centre = np.zeros(case.space.dim)
    return [Job(FLOOR, truth, tuple(float(x) for x in case.space.to_action(truth)), 0, "floor"),
            Job(CENTRE, case.space.to_values(centre), tuple(float(x) for x in centre), 1,
                "centre")]


def reference_settings(case_version: ArtifactVersion) -> dict:
    """What the reference campaign is bound to (checked by the flow before it runs)."""
    return {"case_artifact": case_version.ref(), "agent": REFERENCE_AGENT, "seed": 0,
            "agent_settings": {}, "scoring_version": SCORING_VERSION}


def run_references(case: Case, storage: str, reference: str, runner,
                   observations=None, floor: Mapping[str, float] | None = None,
                   simulator_of: Callable[[Job], object] | None = None) -> dict[int, dict]:
    """Simulate, on the started task ``runner``, the reference calls not yet journaled under
    ``reference`` (a campaign of its own, bound by the flow to :func:`reference_settings`)
    and return both records by index. With ``observations`` a record keeps the simulated
    value of every row, so that the campaign's objective scores it (a reference journaled
    before records kept them has no likelihood). ``floor`` and ``simulator_of`` (a job's
    simulator) are a latent case's (:mod:`tasks.latent`)."""
    journal = EvaluationJournal(ArtifactStore(storage), reference)
    done = {r["index"] for r in journal.rows()}
    futures = [runner.submit(simulate, simulate_parameters(
        case, job, storage, reference, 0, REFERENCE_AGENT, observations,
        simulator=simulator_of(job) if simulator_of else None))
        for job in reference_jobs(case, floor) if job.index not in done]
    for f in futures:
        f.result()
    return {r["index"]: r for r in journal.rows()}
