"""One simulator call as a Prefect task; its record goes to the campaign journal atomically."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from tasks.naming import simulate_run_name
from hmcore.calibration.calls import Job
from hmcore.model.case import Case
from hmcore.scoring.evaluation import evaluate, simulator_for
from hmcore.reporting.report import to_jsonable
from storage import ArtifactStore, EvaluationJournal



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


def evaluate_or_raise_transient(case: Case, values: dict[str, float], run_dir: Path):
    """Evaluate ``values`` in ``run_dir`` (an :class:`~hmcore.scoring.evaluation.Evaluation`); a
    transient failure (killed by a signal) raises while Prefect still has retries left; a
    timeout is not retried (a model that is too slow is as slow the second time).
    Returns the evaluation and the attempt number."""
    from prefect.runtime import task_run

    simulator = simulator_for(case)
    ev = evaluate(case, values, run_dir, simulator)
    attempt = int(getattr(task_run, "run_count", 1) or 1)
    if ev.failure is not None and ev.failure.transient and attempt <= 2:
        raise TransientSimulationError(ev.reason)
    return ev, attempt


def observation_set(case: Case):
    """The case's measured rows with their noise level (built once per campaign): what the
    whitened residual vector of each call is made from, for the methods that need it."""
    from hmcore.scoring.observations import ObservationSet

    return ObservationSet.from_case(case)


def simulate_parameters(case: Case, job: Job, store_root: str, campaign: str, seed: int,
                        agent: str, observations=None) -> dict:
    """The keyword arguments of :func:`simulate`, for a task runner's ``submit``."""
    return {"case": case, "job": job, "store_root": store_root, "campaign": campaign,
            "seed": seed, "agent": agent, "observations": observations}


@task(name="simulate", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=1,
      retry_condition_fn=retry_transient, task_run_name=simulate_run_name)
def simulate(case: Case, job: Job, store_root: str, campaign: str, seed: int, agent: str,
             observations=None) -> dict:
    """Evaluate ``job`` and journal the record; transient failures raise to be retried. With
    ``observations`` (an ObservationSet) the record also holds ``residuals``, the whitened
    residual vector of the fitted history (least-squares and ensemble methods use it).
    A call already journaled (its worker died after writing the record, and the cluster
    reran it) returns the journaled record: never simulated or recorded twice."""
    store = ArtifactStore(store_root)
    journaled = EvaluationJournal(store, campaign).get(job.index)
    if journaled is not None:  # a rerun of a call whose worker died after journaling it
        return journaled
    run_dir = fresh_dir(Path(store_root) / campaign / "runs" / f"{job.index:06d}")
    ev, attempt = evaluate_or_raise_transient(case, job.values, run_dir)
    extra = {}
    if observations is not None and ev.responses is not None:
        extra["residuals"] = observations.residual_vector(ev.responses, "fit").tolist()
    record = to_jsonable({"index": job.index, "lane": job.lane, "phase": job.phase,
                          "action": list(job.action), "seed": seed, "agent": agent,
                          "attempts": attempt, "finished_at": time.time(),
                          "host": socket.gethostname(), "host_pid": os.getpid(),  # who ran it
                          **ev.to_record(), **extra})
    EvaluationJournal(store, campaign).record(job.index, record)
    return record
