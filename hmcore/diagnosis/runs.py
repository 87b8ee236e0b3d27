"""The simulations of a diagnosis: a simulated point, its scores, and the budgeted calls.

The simulator is never run here: ``evaluate_batch(case, values_list, step) -> results`` is
injected (results are :class:`hmcore.scoring.evaluation.Evaluation`-like: ``status``, ``E``,
``E_heldout``, ``responses``, ``sim_time_s``, ``reason``); :func:`local_evaluator` is a plain
thread-pool one. :class:`Simulations` counts every call of one round against its budget
(``DiagnosisSettings.budget``) and turns each result into a :class:`Run`: its whitened
residual vectors under a given noise model.
"""

from __future__ import annotations

import itertools
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from hmcore.model.case import Case
from hmcore.scoring.alignment import align
from hmcore.scoring.evaluation import evaluate, score_responses
from hmcore.scoring.misfit import category_ranges, misfit
from hmcore.scoring.observations import ObservationSet

EvaluateBatch = Callable[[Case, list[dict[str, float]], str], list[Any]]


def local_evaluator(run_root: Path, workers: int = 2, simulator=None) -> EvaluateBatch:
    """``evaluate_batch`` running :func:`hmcore.scoring.evaluation.evaluate` on a thread pool.

    Run directories are ``run_root/<step>-<n>`` (never reused); at most ``workers`` at once.
    """
    run_root = Path(run_root)
    counter = itertools.count()
    lock = threading.Lock()

    def evaluate_batch(case: Case, values_list: list[dict[str, float]], step: str = "run"):
        with lock:
            dirs = [run_root / f"{step}-{next(counter):05d}" for _ in values_list]
        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            return list(pool.map(lambda a: evaluate(case, a[0], a[1], simulator),
                                 zip(values_list, dirs)))

    return evaluate_batch


def _ok(result) -> bool:
    status = getattr(result, "status", None)
    status = getattr(status, "value", status)
    return status != "FAIL" and getattr(result, "responses", None) is not None


@dataclass(frozen=True)
class Run:
    """A simulated point of the diagnosis: values, its residual vectors and scores."""

    values: dict[str, float]
    result: Any
    r_fit: np.ndarray | None
    """Whitened residuals of the fitted history (None: the run failed)."""
    r_heldout: np.ndarray | None
    """Whitened residuals of the held-back history."""

    @property
    def ok(self) -> bool:
        return self.r_fit is not None

    @property
    def ssr_fit(self) -> float:
        return float(self.r_fit @ self.r_fit) if self.ok else math.inf

    @property
    def ssr_heldout(self) -> float:
        return float(self.r_heldout @ self.r_heldout) if self.ok else math.inf

    @property
    def responses(self) -> pd.DataFrame | None:
        return getattr(self.result, "responses", None)


def rescore(run: Run, obs: ObservationSet) -> Run:
    """``run`` with its whitened residual vectors under the noise model ``obs``."""
    if not _ok(run.result):
        return Run(run.values, run.result, None, None)
    z = obs.standardized(run.result.responses)
    return Run(run.values, run.result, obs.whiten(z, "fit"), obs.whiten(z, "heldout"))


def run_scores(case: Case, run: Run) -> dict:
    """Misfit E (fitted and held back), per response and per well and response, and the
    whitened SSRs of a run."""
    s = score_responses(case, run.responses)
    return {"E": s["E"], "E_heldout": s["E_heldout"], "per_response": s["per_response"],
            "per_well_response": s["per_well_response"], "ssr_fit": run.ssr_fit,
            "ssr_heldout": run.ssr_heldout}


def heldout_per_well(case: Any, responses: pd.DataFrame | None) -> dict:
    """Held-back misfit E per well and response of ``responses`` (empty when the case holds
    nothing back or the run failed)."""
    held = case.heldout_observed
    if held.empty or responses is None:
        return {}
    ha = align(held, responses, case.time_tolerance_days)
    return misfit(ha.pairs, "mean", 0.0, category_ranges(case.observed)).per_well_response


class Simulations:
    """The simulator calls of one round: every call through the injected ``evaluate_batch``,
    counted (``n_runs``, ``sim_time_s``: the simulators' own seconds) against ``budget``
    (None: no cap). The one mutable object of a round: a meter."""

    def __init__(self, evaluate_batch: EvaluateBatch, budget: int | None,
                 log: Callable[[str], None]):
        self.evaluate_batch = evaluate_batch
        self.budget = budget
        self.log = log
        self.n_runs = 0
        self.sim_time_s = 0.0

    def left(self, reserve: int = 0) -> int | None:
        """Simulator calls left of the budget after ``reserve`` more (None: no budget)."""
        return None if self.budget is None else self.budget - self.n_runs - reserve

    def run(self, case: Case, values_list: list[dict[str, float]], step: str,
            obs: ObservationSet) -> list[Run]:
        """Simulate ``values_list`` on ``case`` (run directories named after ``step``) and
        whiten the residuals under ``obs``. Every step checks the budget before it asks, so a
        request past it is a bug (RuntimeError)."""
        if not values_list:
            return []
        left = self.left()
        if left is not None and len(values_list) > left:
            raise RuntimeError(f"{step}: {len(values_list)} simulations asked for with "
                               f"{left} of the budget {self.budget} left")
        t0 = time.perf_counter()
        results = self.evaluate_batch(case, values_list, step)
        self.n_runs += len(values_list)
        runs = []
        for values, res in zip(values_list, results):
            self.sim_time_s += float(getattr(res, "sim_time_s", 0.0) or 0.0)
            runs.append(rescore(Run(dict(values), res, None, None), obs))
        self.log(f"{step}: {len(values_list)} runs in {time.perf_counter() - t0:.1f} s "
                 f"({sum(r.ok for r in runs)} ok)")
        return runs
