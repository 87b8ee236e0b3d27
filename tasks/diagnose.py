"""The diagnosis's simulator calls, journaled, and the storing of a step's artifacts.

Every run the diagnosis asks for is a :func:`tasks.simulate.simulate` task, journaled under its
number in the order the runs are asked for (0, 1, 2...) in a journal of the diagnosis's own
(:func:`diagnosis_journal`). The diagnosis is deterministic given its inputs, so a diagnosis
started again with the same command asks for the same runs in the same order: a run already
journaled is replayed from its record instead of simulated (:class:`JournaledRuns`).
"""

from __future__ import annotations

import itertools
import threading
from typing import Any

from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.calibration.calls import Job
from hmcore.model.case import Case
from hmcore.scoring.evaluation import Evaluation
from storage import (
    DIAGNOSIS_RUNS,
    ArtifactStore,
    ArtifactVersion,
    EvaluationJournal,
    code_version,
    sha256_json,
)
from tasks.simulate import Destination, evaluation_of, same_values, simulate, simulate_parameters

DIAGNOSIS_AGENT = "diagnosis"
"""The ``agent`` of a diagnosis's journaled runs."""


def diagnosis_journal(inputs: dict[str, Any]) -> str:
    """The name of the journal of a diagnosis with these ``inputs`` (everything its runs depend
    on: the case's files, the settings, the values it starts from, the scoring rules): another
    diagnosis stored under the same campaign, with other inputs, has another journal."""
    return f"diagnosis-{sha256_json(inputs)[:16]}"


def diagnosis_destination(journal: str) -> Destination:
    """Where a diagnosis's runs go: the journal ``journal`` of its campaign, run directories
    ``diagnosis-runs/<step>-<n:05d>``, records with the responses table."""
    return Destination(journal=journal, runs=DIAGNOSIS_RUNS, run_name="{phase}-{index:05d}",
                       responses=True)


class JournaledRuns:
    """The diagnosis's ``evaluate_batch(case, values_list, step)`` on a started task ``runner``:
    numbers the runs in the order asked for, replays those ``journal`` holds and submits the
    others as ``simulate`` tasks, all of a batch at once. A journaled run whose values are not
    the ones asked for is refused (the journal is never mixed): since the inputs name the
    journal, the diagnosis that made it ran other code."""

    def __init__(self, storage: str, campaign: str, journal: str, runner):
        self.storage, self.campaign, self.runner = storage, campaign, runner
        self.destination = diagnosis_destination(journal)
        self.journal = EvaluationJournal(ArtifactStore(storage), campaign, journal)
        self.journaled = len(self.journal.indices())
        """Runs journaled when the diagnosis started (a killed one's, started again)."""
        self.replayed = 0
        self._counter = itertools.count()
        self._lock = threading.Lock()

    def __call__(self, case: Case, values_list: list[dict[str, float]],
                 step: str = "run") -> list[Evaluation]:
        with self._lock:
            jobs = [Job(next(self._counter), dict(v), (), 0, step) for v in values_list]
        records = {}
        for job in jobs:  # every replay checked before anything new runs
            record = self.journal.get(job.index)
            if record is not None:
                records[job.index] = self._replay(record, job)
        futures = {job.index: self.runner.submit(simulate, simulate_parameters(
                       case, job, self.storage, self.campaign, 0, DIAGNOSIS_AGENT,
                       destination=self.destination))
                   for job in jobs if job.index not in records}
        self.replayed += len(records)
        records.update({i: f.result() for i, f in futures.items()})
        return [evaluation_of(records[job.index]) for job in jobs]

    def _replay(self, record: dict, job: Job) -> dict:
        if not same_values(record, job.values):
            raise RuntimeError(
                f"the diagnosis diverged at run {job.index} ({job.phase}): "
                f"{self.journal.path(job.index)} holds a run of {record.get('params')}, the "
                f"diagnosis asks for {job.values}; the journal is kept as it is - remove "
                f"{self.journal.directory} to start this diagnosis afresh")
        return record


@task(name="store-diagnosis-step", cache_policy=NO_CACHE)
def store_step(store_root: str, campaign: str, step: str, inputs: dict[str, Any],
               files: dict[str, Any]) -> ArtifactVersion:
    """Store one diagnosis step's files as a versioned artifact ``campaign/step/vN``."""
    return ArtifactStore(store_root).put_files(campaign, step, inputs, files, code_version())
