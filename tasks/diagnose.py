"""Prefect tasks of the diagnosis: one simulator call per task, and storing a step's artifacts."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.model.case import Case
from hmcore.scoring.evaluation import Evaluation
from storage import ArtifactStore, ArtifactVersion, code_version
from tasks.simulate import evaluate_or_raise_transient, fresh_dir, retry_transient


@task(name="diagnosis-simulate", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=1,
      retry_condition_fn=retry_transient)
def simulate_values(case: Case, values: dict[str, float], run_dir: str) -> Evaluation:
    """Evaluate ``values`` of ``case``'s space in a fresh run directory; a transient failure
    (timeout, killed) raises so that Prefect retries it."""
    return evaluate_or_raise_transient(case, values, fresh_dir(Path(run_dir)))[0]


@task(name="store-diagnosis-step", cache_policy=NO_CACHE)
def store_step(store_root: str, campaign: str, step: str, inputs: dict[str, Any],
               files: dict[str, Any]) -> ArtifactVersion:
    """Store one diagnosis step's files as a versioned artifact ``campaign/step/vN``."""
    return ArtifactStore(store_root).put_files(campaign, step, inputs, files, code_version())
