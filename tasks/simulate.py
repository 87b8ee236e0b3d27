"""One simulator call as a Prefect task, the one every flow submits (a campaign's calls, the
reference runs of a campaign and a benchmark, a diagnosis's runs): its record goes to a
journal atomically, so a call already journaled is never simulated again.

Where a call's record and run directory go is its :class:`Destination`: a campaign's calls go
to the campaign's journal (``evaluations/<index:06d>.json``, runs in ``runs/<index:06d>``); a
diagnosis's to a journal of its own, runs in ``diagnosis-runs/<step>-<n:05d>``, each record
with the simulated responses table, so that a restarted diagnosis replays a run from its
record alone (:func:`evaluation_of`).
"""

from __future__ import annotations

import math
import os
import socket
import time
from dataclasses import dataclass, replace
from pathlib import Path

import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.runtime import task_run

from hmcore.calibration.calls import Job
from hmcore.model.case import Case
from hmcore.scoring.evaluation import Evaluation, evaluate, simulator_for
from hmcore.scoring.observations import ObservationSet
from hmcore.simulation.simulator import Simulator
from storage import RUNS, ArtifactStore, EvaluationJournal, to_jsonable
from storage.space import full_disk, require_store
from tasks.naming import simulate_run_name

VALUES_RTOL = 1e-9
"""Relative tolerance of :func:`same_values`: a rerun computes the values it asks for by the
same arithmetic, so they agree to the last bits; this only forgives the last bits."""


@dataclass(frozen=True)
class Destination:
    """Where the calls of one journal go in the store of their campaign: the records (the
    campaign's journal, or its other journal named ``journal``), the run directories (folder
    ``runs``, each named by ``run_name`` from the call's ``index`` and ``phase``) and whether
    a record keeps the simulated responses table (``responses``)."""

    journal: str | None = None
    runs: str = RUNS
    run_name: str = "{index:06d}"
    responses: bool = False

    def run_dir(self, store: ArtifactStore, campaign: str, job: Job) -> Path:
        """The run directory of ``job`` (a fresh one: see :func:`fresh_dir`)."""
        name = self.run_name.format(index=job.index, phase=job.phase)
        return fresh_dir(store.work_dir(campaign, self.runs) / name)


CAMPAIGN = Destination()
"""A campaign's calls (and its reference runs): ``evaluations/`` and ``runs/<index:06d>``."""


class TransientSimulationError(RuntimeError):
    """A failure worth retrying (:attr:`FailureKind.transient`: killed from outside; a lost
    worker is rerun by the cluster itself): Prefect retries only this exception."""


def retry_transient(task, task_run, state) -> bool:
    """Prefect retry condition: retry only a :class:`TransientSimulationError`."""
    try:
        state.result()
    except TransientSimulationError:
        return True
    except Exception:
        return False
    return False


def fresh_dir(path: Path) -> Path:
    """``path`` or, when a previous attempt left it, ``path.2``, ``path.3``... (never reused)."""
    candidate, attempt = Path(path), 1
    while candidate.exists():
        attempt += 1
        candidate = Path(path).with_name(f"{Path(path).name}.{attempt}")
    return candidate


def evaluate_or_raise_transient(case: Case, values: dict[str, float], run_dir: Path,
                                simulator: Simulator | None = None):
    """Evaluate ``values`` in ``run_dir`` (an :class:`~hmcore.scoring.evaluation.Evaluation`)
    with ``simulator`` (default: the case's); a transient failure (killed by a signal) raises
    while Prefect still has retries left; a timeout is not retried (a model that is too slow
    is as slow the second time). Returns the evaluation and the attempt number."""
    simulator = simulator or simulator_for(case)
    ev = evaluate(case, values, run_dir, simulator)
    attempt = int(getattr(task_run, "run_count", 1) or 1)
    if ev.failure is not None and ev.failure.transient and attempt <= 2:
        raise TransientSimulationError(ev.reason)
    return ev, attempt


def observation_set(case: Case) -> ObservationSet:
    """The case's measured rows with their noise level (built once per campaign): the rows
    whose simulated values each call's record keeps."""
    return ObservationSet.from_case(case)


def same_values(record: dict, values: dict[str, float]) -> bool:
    """Whether the journaled ``record`` is a run of these parameter ``values`` (the same names,
    the same numbers to :data:`VALUES_RTOL`)."""
    stored = record.get("params") or {}
    return set(stored) == set(values) and all(
        stored[k] is not None and math.isclose(float(stored[k]), float(values[k]),
                                               rel_tol=VALUES_RTOL, abs_tol=VALUES_RTOL)
        for k in values)


def evaluation_of(record: dict) -> Evaluation:
    """The evaluation a journaled record describes, with its responses table when the record
    keeps it (see :class:`Destination`): the same, to the last bit, as the one simulated."""
    ev = Evaluation.from_record(record)
    table = record.get("responses")
    if table is None:
        return ev
    frame = pd.DataFrame(dict(zip(table["columns"], table["values"], strict=True)))
    return replace(ev, responses=frame)


def responses_record(responses: pd.DataFrame) -> dict:
    """A responses table as a record holds it: the column names in order (a record's keys are
    stored sorted) and each column's values."""
    return {"columns": [str(c) for c in responses.columns],
            "values": [responses[c].tolist() for c in responses.columns]}


BATCH_JOB_VARIABLES = ("SLURM_JOB_ID", "PBS_JOBID", "LSB_JOBID")
"""Where Slurm, PBS and LSF tell a job's processes their job id."""


def batch_job() -> dict[str, str]:
    """``{"batch_job": id}`` when this process runs in a batch job (a Dask worker of
    ``--cluster``), so that the journal tells which job ran each call; else ``{}``."""
    for name in BATCH_JOB_VARIABLES:
        if os.environ.get(name):
            return {"batch_job": os.environ[name]}
    return {}


def simulate_parameters(case: Case, job: Job, store_root: str, campaign: str, seed: int,
                        agent: str, observations=None,
                        destination: Destination = CAMPAIGN,
                        simulator: Simulator | None = None) -> dict:
    """The keyword arguments of :func:`simulate`, for a task runner's ``submit``."""
    return {"case": case, "job": job, "store_root": store_root, "campaign": campaign,
            "seed": seed, "agent": agent, "observations": observations,
            "destination": destination, "simulator": simulator}


@task(name="simulate", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=1,
      retry_condition_fn=retry_transient, task_run_name=simulate_run_name)
def simulate(case: Case, job: Job, store_root: str, campaign: str, seed: int, agent: str,
             observations=None, destination: Destination = CAMPAIGN,
             simulator: Simulator | None = None) -> dict:
    """Evaluate ``job`` and journal the record (where: ``destination``); transient failures
    raise to be retried. ``simulator``: the case's own by default (an ensemble member's run
    wraps it, :class:`hmcore.fields.members.MemberSimulator`). With ``observations`` (an ObservationSet) the record also holds
    ``simulated``, the simulated value of every row of the set (NaN where no simulated time
    is within the tolerance), from which the campaign's objective scores the call and
    refines the noise (:mod:`hmcore.calibration.objective`); with ``destination.responses``, ``responses``, the simulated
    table (:func:`responses_record`). A call already journaled (its worker died after writing
    the record, and the cluster reran it) returns the journaled record: never simulated or
    recorded twice. A store whose folder is gone, or a failed call on a full disk, raises
    ``OSError`` (:mod:`storage.space`): the call is not journaled and runs again on resume."""
    store = ArtifactStore(require_store(store_root))  # removed mid-run: a fault, not a call
    journal = EvaluationJournal(store, campaign, destination.journal)
    journaled = journal.get(job.index)
    if journaled is not None:  # a rerun of a call whose worker died after journaling it
        return journaled
    run_dir = destination.run_dir(store, campaign, job)
    ev, attempt = evaluate_or_raise_transient(case, job.values, run_dir, simulator)
    if ev.failure is not None and (fault := full_disk(store_root)) is not None:
        raise fault  # the disk failed, not the model: not journaled, run again on resume
    extra = {}
    if observations is not None and ev.responses is not None:
        extra["simulated"] = observations.simulated(ev.responses).tolist()
    if destination.responses and ev.responses is not None:
        extra["responses"] = responses_record(ev.responses)
    record = to_jsonable({"index": job.index, "lane": job.lane, "phase": job.phase,
                          "action": list(job.action), "seed": seed, "agent": agent,
                          "attempts": attempt, "finished_at": time.time(),
                          "host": socket.gethostname(), "host_pid": os.getpid(),  # who ran it
                          **batch_job(), **ev.to_record(), **extra})
    journal.record(job.index, record)
    return record
