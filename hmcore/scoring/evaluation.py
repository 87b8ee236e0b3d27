"""One evaluation: parameter values -> per-run deck -> simulator -> responses -> score.

States follow Optuna's trials: ``COMPLETE`` (scored), ``INVALID`` (simulated and scored but
physically invalid: penalised, never best), ``FAIL`` (no usable result: the reason is recorded,
``E`` is NaN, never an invented score). ``reward = -E - P`` for scored runs and
``-failure_penalty - P`` for failures, so a learning agent always gets a finite signal.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
import pandas as pd

from hmcore.errors import FailureKind, SimulationError
from hmcore.model.case import Case
from hmcore.model.run_deck import prepare_run_deck
from hmcore.scoring.alignment import align
from hmcore.scoring.metrics import compute_metrics
from hmcore.scoring.misfit import category_ranges, misfit
from hmcore.scoring.physics import check_physics, check_responses
from hmcore.scoring.record_format import failure_of
from hmcore.simulation import simulator as simulators  # make_simulator looked up per call
from hmcore.simulation.responses import last_time, read_responses
from hmcore.simulation.simulator import Simulator

SCORING_VERSION = 2
"""The rules a call is scored by (misfit, metrics, physics checks). A campaign is bound to the
version it started with: records scored by other rules are never mixed in one campaign.
1: no cell physics checks, and a ratio of 0 to 0 counted a match; 2: the paper's metrics and
the physics checks of :mod:`hmcore.scoring.physics`."""


class Status(str, Enum):
    COMPLETE = "COMPLETE"
    INVALID = "INVALID"
    FAIL = "FAIL"


@dataclass
class Evaluation:
    """Everything one simulator call produced (serialisable with :meth:`to_record`)."""

    params: dict[str, float]
    status: Status
    E: float
    penalty: float
    reward: float
    per_response: dict[str, float] = field(default_factory=dict)
    coverage: float = float("nan")
    wall_time_s: float = 0.0
    sim_time_s: float = 0.0
    run_dir: str = ""
    reason: str = ""
    violations: tuple[str, ...] = ()
    E_heldout: float = float("nan")
    metrics: dict = field(default_factory=dict)
    heldout_metrics: dict = field(default_factory=dict)
    responses: pd.DataFrame | None = field(default=None, repr=False)
    violation_kinds: tuple[str, ...] = ()  # hmcore.scoring.physics.Check values, one per violation
    failure: FailureKind | None = None      # why a FAIL gave no result (None otherwise)
    E_worst: float = float("nan")           # the worst well-response loss of the fitted part
    peak_rss_bytes: float = float("nan")    # the simulator's peak resident memory (NaN: unknown)

    @property
    def selectable(self) -> bool:
        """Only complete, valid, finite runs may ever be called best."""
        return self.status is Status.COMPLETE and math.isfinite(self.E)

    @classmethod
    def from_record(cls, record: dict) -> "Evaluation":
        """The evaluation a journaled record describes (no responses table)."""
        def num(key: str) -> float:
            v = record.get(key)
            return float("nan") if v is None else float(v)

        return cls(dict(record["params"]), Status(record["status"]), num("E"), num("penalty"),
                   num("reward"), dict(record.get("per_response") or {}), num("coverage"),
                   num("wall_time_s"), num("sim_time_s"), record.get("run_dir", ""),
                   record.get("reason", ""), tuple(record.get("violations") or ()),
                   num("E_heldout"), dict(record.get("metrics") or {}),
                   dict(record.get("heldout_metrics") or {}),
                   violation_kinds=tuple(record.get("violation_kinds") or ()),
                   failure=failure_of(record), E_worst=num("E_worst"),
                   peak_rss_bytes=num("peak_rss_bytes"))

    def to_record(self) -> dict:
        """Flat JSON-friendly record (no responses table)."""
        rec = asdict(self)
        rec.pop("responses")
        rec["status"] = self.status.value
        rec["violations"] = list(self.violations)
        rec["violation_kinds"] = list(self.violation_kinds)
        rec["failure"] = self.failure.value if self.failure is not None else None
        return rec



def _bytes(peak: int | None) -> float:
    return float("nan") if peak is None else float(peak)


def simulator_for(case: Case) -> Simulator:
    """The case's simulator: its backend, timeout, threads and processes per run, stop step."""
    return simulators.make_simulator(case.simulator.backend, case.simulator.timeout_s,
                                     case.simulator.threads, case.stop_step,
                                     case.simulator.processes)


def score_responses(case: Case, responses: pd.DataFrame) -> dict:
    """Misfit and metrics of simulated ``responses`` against the case's history.

    Returns E, per_response, coverage and metrics on the fitted part, and E_heldout with
    heldout metrics on the held-back part (NaN/empty when nothing is held back).
    """
    ranges = category_ranges(case.observed)
    fit = align(case.fit_observed, responses, case.time_tolerance_days)
    m = misfit(fit.pairs, case.misfit.variant, case.misfit.robust_lambda, ranges)
    out = {"E": m.E, "per_response": m.per_response, "per_well_response": m.per_well_response,
           "E_worst": m.worst,
           "coverage": fit.coverage, "metrics": compute_metrics(fit.pairs),
           "E_heldout": float("nan"), "heldout_metrics": {}, "pairs": fit.pairs}
    held = case.heldout_observed
    if not held.empty:
        ha = align(held, responses, case.time_tolerance_days)
        out["E_heldout"] = misfit(ha.pairs, case.misfit.variant, case.misfit.robust_lambda,
                                  ranges).E
        out["heldout_metrics"] = compute_metrics(ha.pairs)
    return out


def evaluate(case: Case, values: dict[str, float], run_dir: Path,
             simulator: Simulator | None = None) -> Evaluation:
    """Simulate ``values`` (physical units) in ``run_dir`` and score the result."""
    start = time.perf_counter()
    simulator = simulator or simulator_for(case)
    phys = check_physics(values, case.space, case.info, case.physics)
    fail_reward = -case.physics.failure_penalty - phys.penalty

    def failed(kind: FailureKind, message: str, sim_time: float = 0.0,
               peak: int | None = None) -> Evaluation:
        return Evaluation(dict(values), Status.FAIL, float("nan"),
                          case.physics.failure_penalty + phys.penalty, fail_reward,
                          wall_time_s=time.perf_counter() - start, sim_time_s=sim_time,
                          run_dir=str(run_dir), reason=f"{kind.value}: {message}",
                          violations=phys.violations, violation_kinds=phys.kinds,
                          failure=kind, peak_rss_bytes=_bytes(peak))

    if not phys.runnable:
        return failed(FailureKind.NOT_RUNNABLE, "physically impossible, not simulated: "
                      + "; ".join(phys.violations))
    deck = prepare_run_deck(case.deck, values, case.space, Path(run_dir), case.info)
    sim_start = time.perf_counter()
    try:
        result = simulator.run(deck, Path(run_dir))
    except SimulationError as exc:
        tail = exc.log_tail.strip().splitlines()[-1:] if exc.log_tail else []
        return failed(FailureKind(exc.reason), exc.message + (f" | {tail[0]}" if tail else ""),
                      time.perf_counter() - sim_start)
    try:  # a summary the simulator left garbled, empty or half-written is a failed call
        end = last_time(result.summary_path)
        responses = read_responses(result.summary_path, sorted(case.info.wells))
    except Exception as exc:  # opm.io raises RuntimeError, ValueError, IndexError...
        return failed(FailureKind.UNREADABLE_OUTPUT, f"cannot read {result.summary_path.name}: "
                      f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}",
                      result.wall_time_s, result.peak_rss_bytes)
    if end < case.run_end_days - 1e-3:
        return failed(FailureKind.NO_CONVERGENCE, f"stopped at day {end} of "
                      f"{case.run_end_days}", result.wall_time_s, result.peak_rss_bytes)
    if not responses.empty and not np.isfinite(responses["value"].to_numpy(float)).all():
        bad = responses[~np.isfinite(responses["value"].to_numpy(float))]
        return failed(FailureKind.INVALID_VALUES, f"{len(bad)} simulated values are not finite "
                      f"(first: {bad.quantity.iloc[0]} of {bad.well.iloc[0]} at day "
                      f"{bad.days.iloc[0]:g})", result.wall_time_s, result.peak_rss_bytes)
    s = score_responses(case, responses)
    if not math.isfinite(s["E"]):
        return failed(FailureKind.NO_MATCH, "no simulated record within the time tolerance of "
                      "any observation", result.wall_time_s, result.peak_rss_bytes)
    phys = phys + check_responses(responses, case.info, case.physics)
    status = Status.COMPLETE if phys.valid else Status.INVALID
    return Evaluation(dict(values), status, s["E"], phys.penalty, -s["E"] - phys.penalty,
                      s["per_response"], s["coverage"], time.perf_counter() - start,
                      result.wall_time_s, str(run_dir), "; ".join(phys.violations),
                      phys.violations, s["E_heldout"], s["metrics"], s["heldout_metrics"],
                      responses, phys.kinds, E_worst=s["E_worst"],
                      peak_rss_bytes=_bytes(result.peak_rss_bytes))
