"""One simulator call as a Prefect task; its record goes to the campaign journal atomically."""

from __future__ import annotations

from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.calibration import Job
from hmcore.case import Case
from hmcore.evaluation import evaluate
from hmcore.report import to_jsonable
from hmcore.simulator import make_simulator
from storage import ArtifactStore, EvaluationJournal

TRANSIENT_REASONS = ("timeout", "killed")  # worth retrying; crashes and parse errors are not


class TransientSimulationError(RuntimeError):
    """A failure worth retrying (timeout, killed): Prefect retries only this exception."""


def _retry_transient(task, task_run, state) -> bool:
    try:
        state.result()
    except TransientSimulationError:
        return True
    except Exception:
        return False
    return False


def fresh_run_dir(run_root: Path, index: int) -> Path:
    """``runs/000012`` or, when a previous attempt left it, ``runs/000012.2`` etc. (never reused)."""
    base = run_root / f"{index:06d}"
    candidate, attempt = base, 1
    while candidate.exists():
        attempt += 1
        candidate = base.with_name(f"{base.name}.{attempt}")
    return candidate


@task(name="simulate", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=1,
      retry_condition_fn=_retry_transient)
def simulate(case: Case, job: Job, store_root: str, campaign: str, seed: int, agent: str) -> dict:
    """Evaluate ``job`` and journal the record; transient failures raise to be retried."""
    from prefect.runtime import task_run

    store = ArtifactStore(store_root)
    run_dir = fresh_run_dir(Path(store_root) / campaign / "runs", job.index)
    simulator = make_simulator(case.simulator.backend, case.simulator.timeout_s)
    ev = evaluate(case, job.values, run_dir, simulator)
    attempt = int(getattr(task_run, "run_count", 1) or 1)
    if ev.status.value == "FAIL" and ev.reason.split(":")[0] in TRANSIENT_REASONS and attempt <= 2:
        raise TransientSimulationError(ev.reason)
    record = to_jsonable({"index": job.index, "lane": job.lane, "phase": job.phase,
                          "action": list(job.action), "seed": seed, "agent": agent,
                          "attempts": attempt, **ev.to_record()})
    EvaluationJournal(store, campaign).record(job.index, record)
    return record
