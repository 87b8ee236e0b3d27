"""Bounded least squares on the whitened residuals of the fitted history, multi-start: the
ask/tell solver of :mod:`hmcore.calibration.trust_region_reflective` (scipy's trust-region
reflective algorithm, ``least_squares(method="trf")``, on [-1, 1]^d), driven here over the
budgeted calls.

The residual vector of a call is the noise-whitened ``(simulated - observed) / sigma`` of the
case's :class:`hmcore.scoring.observations.ObservationSet` (the campaign stores it in the
record), plus one entry ``sqrt(P * chi2 / E)`` for a physics penalty P, so that the sum of
squares weighs a penalty as the reward ``-E - P`` does. The Jacobian is a forward difference
of step ``FD_STEP`` in action units, its d runs sent to the workers together; every run is a
call. A failed run has no residuals: at the current point it ends that descent, in a Jacobian
its column is left at 0. When a descent converges with budget left, a new one starts from a
uniform-random point (the first starts at the box's centre), until the budget is spent.

Workers are not left idle by the serial steps (version 2): each point the solver asks is sent
together with the first W - 1 finite-difference runs of the Jacobian at that point, so that
when the step is accepted (it usually is) those columns are already there. A rejected step
wastes them: W - 1 calls. Version 1 sent the trial point alone, and a 2-worker campaign ran
32 % above the simulator time per worker on PUNQ-S3 (one worker idle at every step).
"""

from __future__ import annotations

import math

import numpy as np

from hmcore.calibration.calls import BudgetedCalls, BudgetExhausted
from hmcore.calibration.registry import VERSIONS
from hmcore.calibration.trust_region_reflective import TrustRegionReflective

FD_STEP = 0.05
VERSION = VERSIONS["lm"]  # what the campaign store binds a lm campaign to


def residuals_of(record: dict) -> np.ndarray | None:
    """The least-squares residuals of a record (None for a failed run)."""
    r = record.get("residuals")
    if r is None or record.get("status") == "FAIL":
        return None
    r = np.nan_to_num(np.asarray(r, float))
    P, E = float(record.get("penalty") or 0.0), record.get("E")
    if P > 0 and E is not None and math.isfinite(E) and E > 0:
        return np.append(r, math.sqrt(P * float(r @ r) / E))
    return np.append(r, 0.0)


class LMDriver:
    name = "lm"
    needs_residuals = True

    def __init__(self, dim: int, seed: int):
        self.dim = dim
        self.rng = np.random.default_rng(seed)
        self.descents: list[dict] = []

    def drive(self, space, evaluate_batch, budget: int, workers: int,
              done: dict[int, dict] | None = None) -> list[dict]:
        calls = BudgetedCalls(space, evaluate_batch, budget, done, self.name)
        x0 = np.zeros(self.dim)
        while calls.left > 0:
            solver = TrustRegionReflective(x0, FD_STEP, max_nfev=calls.left)
            try:
                self._descend(solver, calls, workers)
            except BudgetExhausted:
                break
            self.descents.append({"x": None, "cost": None, "status": "failed run"}
                                 if solver.failed else
                                 {"x": solver.x.tolist(), "cost": float(solver.cost),
                                  "status": int(solver.status)})
            x0 = self.rng.uniform(-1.0, 1.0, self.dim)
        return calls.records

    def _descend(self, solver: TrustRegionReflective, calls: BudgetedCalls,
                 workers: int) -> None:
        """One descent: each point the solver asks goes out with the first W - 1 runs of the
        Jacobian there (version 2); a Jacobian it asks takes the runs already made."""
        residuals: dict[tuple, np.ndarray] = {}  # the residuals at each point asked
        columns: dict[tuple, dict[int, dict]] = {}  # speculative Jacobian runs at a point

        def key_of(x: np.ndarray) -> tuple:
            return tuple(np.round(x, 12))

        while not solver.done:
            points = solver.ask()
            if solver.jacobian_asked:
                runs = dict(columns.get(key_of(solver.x), {}))
                todo = [k for k in range(self.dim) if k not in runs]
                if todo:
                    runs.update(zip(todo, calls.run(np.array(points)[todo], phase="jacobian")))
                solver.tell([(residuals_of(runs[k]), runs[k]) for k in range(self.dim)])
                continue
            (x,) = points
            key = key_of(x)
            if key not in residuals:
                extra = min(max(workers - 1, 0), self.dim, max(calls.left - 1, 0))
                batch = np.vstack([x[None], solver.fd_points(x)[:extra]])
                records = calls.run(batch, phases=["explore"] + ["jacobian"] * extra)
                columns[key] = dict(enumerate(records[1:]))
                r = residuals_of(records[0])
                if r is None:
                    solver.tell([(None, records[0])])  # ends the descent
                    return
                residuals[key] = r
            solver.tell([(residuals[key], None)])
