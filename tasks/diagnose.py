"""Prefect tasks of the diagnosis: one simulator call per task, and storing a step's artifacts."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.case import Case
from hmcore.evaluation import Evaluation, evaluate
from hmcore.simulator import make_simulator
from storage import ArtifactStore, ArtifactVersion, code_version
from tasks.simulate import TRANSIENT_REASONS, TransientSimulationError, _retry_transient


def fresh_dir(path: Path) -> Path:
    """``path`` or, when a previous attempt left it, ``path.2``, ``path.3``... (never reused)."""
    candidate, attempt = Path(path), 1
    while candidate.exists():
        attempt += 1
        candidate = Path(path).with_name(f"{Path(path).name}.{attempt}")
    return candidate


@task(name="diagnosis-simulate", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=1,
      retry_condition_fn=_retry_transient)
def simulate_values(case: Case, values: dict[str, float], run_dir: str) -> Evaluation:
    """Evaluate ``values`` of ``case``'s space in a fresh run directory; a transient failure
    (timeout, killed) raises so that Prefect retries it."""
    from prefect.runtime import task_run

    simulator = make_simulator(case.simulator.backend, case.simulator.timeout_s)
    ev = evaluate(case, values, fresh_dir(Path(run_dir)), simulator)
    attempt = int(getattr(task_run, "run_count", 1) or 1)
    if ev.status.value == "FAIL" and ev.reason.split(":")[0] in TRANSIENT_REASONS and attempt <= 2:
        raise TransientSimulationError(ev.reason)
    return ev


@task(name="store-diagnosis-step", cache_policy=NO_CACHE)
def store_step(store_root: str, campaign: str, step: str, inputs: dict[str, Any],
               files: dict[str, Any]) -> ArtifactVersion:
    """Store one diagnosis step's files as a versioned artifact ``campaign/step/vN``."""
    return ArtifactStore(store_root).put_files(campaign, step, inputs, files, code_version())
