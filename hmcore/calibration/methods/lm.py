"""Bounded least squares on the whitened residuals of the fitted history, multi-start: the
ask/tell solver of :mod:`hmcore.calibration.trust_region_reflective` (scipy's trust-region
reflective algorithm, ``least_squares(method="trf")``, on [-1, 1]^d), driven here over the
campaign's calls.

The residual vector of a call is the noise-whitened ``(simulated - observed) / sigma`` of the
case's :class:`hmcore.scoring.observations.ObservationSet` (the campaign stores it in the
record), plus one entry ``sqrt(P * chi2 / E)`` for a physics penalty P, so that the sum of
squares weighs a penalty as the reward ``-E - P`` does. The Jacobian is a forward difference
of step ``FD_STEP`` in action units, its d runs sent to the workers together; every run is a
call. A failed run has no residuals: at the current point it ends that descent, in a Jacobian
its column is left at 0.

Workers are not left idle by the serial steps (version 2): each point the solver asks is sent
together with W - 1 finite-difference runs of the Jacobian at that point, so that when the
step is accepted (it usually is) those columns are already there. A rejected step wastes
them: W - 1 calls. Version 1 sent the trial point alone, and a 2-worker campaign ran 32 %
above the simulator time per worker on PUNQ-S3 (one worker idle at every step).

The Jacobian is not computed anew at every accepted point (version 6): it is updated along
the step by Broyden's secant formula and only :func:`refresh` of its columns (the W - 1 run
beside the trial, at least one) are finite differences at the new point, the columns in
turn; a trial rejected while some columns are secant estimates is followed by finite
differences of those (see :mod:`~hmcore.calibration.trust_region_reflective`). An iteration
near the end of a descent costs W calls instead of d + 1; a descent still starts on a whole
finite-difference Jacobian, and one that ends on the campaign's best call with secant columns
there runs those anew (:meth:`Descent.complete`): the report's identifiability section reads
a whole finite-difference stencil at the best call from the journal
(:mod:`hmcore.reporting.identifiability`).

Calls are spent where they tell something (version 3):

* **Physics checks as the edge of the domain.** Where the campaign knows a point's
  pre-simulation checks (:class:`~hmcore.calibration.calls.PhysicsPrecheck`: the
  porosity-permeability trend, kv/kh, caps, pore volume), a finite-difference step that would
  break a check its base passes goes the other way, and a trial point that would break one
  the current point passes is not simulated (the solver shrinks its step: see
  :mod:`~hmcore.calibration.trust_region_reflective`). A Jacobian run that comes back
  penalised or failed where its base is valid (a check on the simulated responses, which
  nothing predicts) is run once more the other way, when that stays in the box and breaks no
  known check; the other way's run replaces it unless it failed where the first had
  residuals.
* **No point twice.** A point the campaign has simulated is never simulated again (the
  calls hand back its record: :class:`~hmcore.calibration.calls.BudgetedCalls`), and a descent
  whose trial point is one the campaign has simulated is retracing itself: it ends there.
* **Restarts instead of stalls.** A descent ends when it converges (scipy's tolerances; the
  Jacobian scipy computes at the converged point is not asked for), when its start or a trial
  fails to run, when a trial repeats a simulated point, when an accepted trial lowers its sum
  of squares by less than :data:`STALL_FTOL` of it (a new Jacobian there would cost d calls
  for less), or after :data:`STALL_TRIALS` rejected trials in a row; with budget left, the
  next descent starts from a random point (the first starts at the box's centre) that breaks
  no pre-simulation check (up to :data:`START_DRAWS` draws; the first draw when none passes).
  The restarts alternate, the first near the best call so far (a normal draw of
  :data:`NEAR_SCALE` around it: does the basin hold a better point the descent missed?), the
  next anywhere in the box (uniform: is there another basin?), and so on (the versions:
  :data:`hmcore.calibration.registry.VERSIONS`; measured in docs/benchmarks.md).

The residuals are the campaign's objective's (version 4,
:meth:`hmcore.calibration.objective.Objective.residuals`): the whitened ones under the
likelihood, E's own under E. Under the likelihood, the noise the residuals are whitened by is
refined from the best call so far (:meth:`~hmcore.calibration.calls.BudgetedCalls.refine_noise`)
at the end of each descent, and when the calls pass a share of the budget
(:data:`~hmcore.calibration.calls.REFINE_AT`; the descent then ends). A descent that follows a
refinement starts from the best call so far, whose record and finite-difference runs the
campaign already has (no call spent on them), instead of from a random point: the fit goes on
where it was, under the refined noise.
"""

from __future__ import annotations

import numpy as np

from hmcore.calibration.calls import BudgetedCalls, BudgetExhausted
from hmcore.calibration.objective import Objective
from hmcore.calibration.registry import VERSIONS
from hmcore.calibration.trust_region_reflective import STATUS, TrustRegionReflective

FD_STEP = 0.05
VERSION = VERSIONS["lm"]  # what the campaign store binds a lm campaign to
STALL_TRIALS = 3
"""Rejected trials in a row (each a call, and W - 1 speculative Jacobian runs) that end a
descent."""
STALL_FTOL = 1e-3
"""An accepted trial that lowers the descent's sum of squares by less than this fraction of
it ends the descent: on whitened residuals, a chi-square unit or less for a history of a
thousand values, below what the noise lets a fit tell apart."""
START_DRAWS = 20
"""Draws tried for a restart's start point that breaks no pre-simulation check."""
NEAR_SCALE = 0.1
"""Standard deviation, in action units (the box is [-1, 1] on each axis), of a near restart's
start around the best call: two finite-difference steps, a twentieth of the box's width."""


def refresh(workers: int, dim: int) -> int:
    """Jacobian columns computed anew after an accepted step: those run beside the trial
    (W - 1), at least one, at most all ``dim``."""
    return min(max(workers - 1, 1), dim)


def residuals_of(record: dict) -> np.ndarray | None:
    """The least-squares residuals of a record under the E objective, from the record's own
    ``residuals`` (None for a failed run): see :meth:`Objective.residuals`."""
    return Objective().residuals(record)


def broken_at(run: dict, base: dict | None) -> bool:
    """Whether a Jacobian ``run`` came back penalised or failed where its ``base`` is valid."""
    return (base is not None and base.get("status") == "COMPLETE"
            and run.get("status") in ("INVALID", "FAIL"))


class LMDriver:
    name = "lm"
    needs_residuals = True

    def __init__(self, dim: int, seed: int):
        self.dim = dim
        self.rng = np.random.default_rng(seed)
        self.descents: list[dict] = []
        """Each descent's end: its point and cost (None when it failed to run), and why."""
        self.restarts = 0
        """Restarts drawn so far (even: near the best call, odd: anywhere in the box)."""

    def drive(self, calls: BudgetedCalls, workers: int) -> list[dict]:
        x0 = np.zeros(self.dim)
        while calls.left > 0:
            solver = TrustRegionReflective(x0, FD_STEP, max_nfev=calls.left,
                                           breaks=calls.breaks,
                                           refresh=refresh(workers, self.dim))
            descent = Descent(solver, calls, workers)
            try:
                descent.run()
                descent.complete()
            except BudgetExhausted:
                break
            ran = not solver.failed and solver.f is not None
            refined = calls.refine_noise() or descent.refined
            self.descents.append({"x": solver.x.tolist() if ran else None,
                                  "cost": float(solver.cost) if ran else None,
                                  "reason": descent.reason or solver.reason,
                                  "noise_refined": refined})
            best = calls.best() if refined else None
            x0 = (np.clip(np.asarray(best["action"], float), -1.0, 1.0) if best is not None
                  else self._start(calls))
        return calls.records

    def _start(self, calls: BudgetedCalls) -> np.ndarray:
        """A restart's start point: the first of :data:`START_DRAWS` draws that breaks no
        pre-simulation check (the first draw when none passes, or nothing is known before a
        run); near the best call on even restarts (when one ran), anywhere on odd ones."""
        best = calls.best() if self.restarts % 2 == 0 else None
        self.restarts += 1
        centre = None if best is None else np.clip(np.asarray(best["action"], float), -1.0, 1.0)
        first = self._draw(centre)
        if calls.precheck is None or not calls.kinds(first):
            return first
        for _ in range(START_DRAWS - 1):
            x = self._draw(centre)
            if not calls.kinds(x):
                return x
        return first

    def _draw(self, centre: np.ndarray | None) -> np.ndarray:
        """One start point: normal around ``centre`` (clipped to the box), uniform without."""
        if centre is None:
            return self.rng.uniform(-1.0, 1.0, self.dim)
        return np.clip(centre + self.rng.normal(0.0, NEAR_SCALE, self.dim), -1.0, 1.0)


class Descent:
    """One descent of the solver over the campaign's calls (see the module docstring): each
    point the solver asks goes out with the first W - 1 runs of the Jacobian there; a
    Jacobian it asks takes the runs already made. ``reason`` says why it ended, when it was
    this driver's rule (a repeated point, a stall) rather than the solver's."""

    def __init__(self, solver: TrustRegionReflective, calls: BudgetedCalls, workers: int):
        self.solver = solver
        self.calls = calls
        self.workers = workers
        self.dim = solver.x.size
        self.reason = ""
        self.base: dict[tuple, dict] = {}  # the record of each point asked
        self.columns: dict[tuple, dict[int, dict]] = {}  # speculative Jacobian runs at a point
        self.stalled = 0
        self.objective = calls.objective  # the one its sums of squares are under
        self.refined = False  # the noise was refined during the descent (which then ended)

    def residuals(self, record: dict) -> np.ndarray | None:
        return self.calls.objective.residuals(record)

    def _refined_now(self) -> bool:
        """Whether the calls refined the noise (passing a share of the budget) since the
        descent began: the descent then ends (its sums of squares are of the noise before)."""
        if self.calls.objective is not self.objective:
            self.refined = True
            self.reason = "the noise was refined from the best call so far"
        return self.refined

    @staticmethod
    def key_of(x: np.ndarray) -> tuple:
        return tuple(np.round(x, 12))

    def run(self) -> None:
        solver = self.solver
        while not solver.done:
            points = solver.ask()
            if not points:
                return
            if solver.jacobian_asked and solver.status is not None:
                self.reason = STATUS[solver.status]  # scipy's final Jacobian: not needed here
                return
            if solver.jacobian_asked:
                self._jacobian(points)
                if self._refined_now():
                    return
                continue
            (x,) = points
            starting = solver.f is None
            if not starting and self.calls.simulated(x) is not None:
                self.reason = "a trial repeats a point the campaign has simulated"
                return
            record = self._point(x)
            r = self.residuals(record)
            if r is None:
                solver.tell([(None, record)])  # ends the descent
                return
            before = solver.cost
            solver.tell([(r, None)])
            if self._refined_now() or (not starting and self._stalls(before)):
                return

    def complete(self) -> None:
        """When the descent ended on the campaign's best call and some Jacobian columns there
        are secant estimates (or were never run), run those anew (the solver then ends)."""
        solver = self.solver
        best = self.calls.best()
        if best is None or solver.failed or solver.f is None:
            return
        if self.key_of(np.asarray(best["action"], float)) != self.key_of(solver.x):
            return
        if solver.complete():
            self._jacobian(solver.ask())

    def _point(self, x: np.ndarray) -> dict:
        """Simulate the point ``x`` with the W - 1 Jacobian runs the solver would ask first
        there; its record."""
        calls = self.calls
        extra = min(max(self.workers - 1, 0), self.dim, max(calls.left - 1, 0))
        columns = self.solver.refresh_columns(extra)
        batch = np.vstack([x[None], self.solver.fd_points(x)[columns]])
        records = calls.run(batch, phases=["explore"] + ["jacobian"] * extra)
        self.columns[self.key_of(x)] = dict(zip(columns, records[1:]))
        self.base[self.key_of(x)] = records[0]
        return records[0]

    def _jacobian(self, points: list[np.ndarray]) -> None:
        """The Jacobian columns asked at the current point: the speculative runs there and
        the rest; a run broken where its base is valid is run once more the other way."""
        solver, calls = self.solver, self.calls
        key = self.key_of(solver.x)
        asked = solver.columns_asked
        have = self.columns.get(key, {})
        runs = {k: have[k] for k in asked if k in have}
        todo = [i for i, k in enumerate(asked) if k not in runs]
        if todo:
            runs.update(zip([asked[i] for i in todo],
                            calls.run(np.array(points)[todo], phase="jacobian")))
        base = self.base.get(key)
        again = {}
        for k in asked:
            if broken_at(runs[k], base):
                w = solver.reverse_fd(k)
                if w is not None:
                    again[k] = w
        if again:
            redone = calls.run(np.array(list(again.values())), phase="jacobian")
            for k, record in zip(again, redone):
                if not (record.get("status") == "FAIL" and runs[k].get("status") != "FAIL"
                        and solver.reverse_fd(k) is not None):  # back: the first has residuals
                    runs[k] = record
        solver.tell([(self.residuals(runs[k]), runs[k]) for k in asked])

    def _stalls(self, before: float) -> bool:
        """Whether the descent ends after a trial (``before``: the cost it started from): an
        accepted trial that gained less than :data:`STALL_FTOL` (the Jacobian there would cost
        d calls for less), or the :data:`STALL_TRIALS` th rejected trial in a row."""
        cost = self.solver.cost
        if self.solver.done:
            return False
        if cost < before and before - cost < STALL_FTOL * before:
            self.reason = f"an accepted step lowered the sum of squares by less than {STALL_FTOL:g}"
            return True
        self.stalled = 0 if cost < before else self.stalled + 1
        if self.stalled >= STALL_TRIALS:
            self.reason = f"{STALL_TRIALS} trials in a row lowered the sum of squares by none"
            return True
        return False


def jacobian_base(record: dict, records: list[dict]) -> dict | None:
    """The base of a journaled Jacobian run ``record``: the latest earlier non-Jacobian record
    of ``records`` (a campaign's, in call order) one finite-difference step (:data:`FD_STEP`,
    either way) away along one coordinate; None when there is none. What the benchmark of
    spent calls and the tests read a Jacobian run's base from."""
    a = np.asarray(record["action"])
    for other in reversed(records[: record["index"]]):
        if other["phase"] == "jacobian":
            continue
        d = np.abs(a - np.asarray(other["action"]))
        if np.sum(d > 1e-9) == 1 and abs(d.max() - FD_STEP) < 1e-9:
            return other
    return None
