"""Bounded least squares on whitened residuals, by ask/tell: the one solver of the ``lm``
calibration method and of the diagnosis's recalibrations.

The unknowns are scaled coordinates ``u`` in a box (``[-1, 1]`` per coordinate unless told
otherwise); the residual vector ``r(u)`` is what a simulation gives (the noise-whitened
``(simulated - observed) / sigma``). A solver never runs the simulator: ``ask()`` returns the
points to simulate next, ``tell()`` takes their residual vectors (``None`` for a failed run),
paired with a payload the caller wants kept with the point (its run record, say).

What every solver here shares, :class:`AskTellLeastSquares`:

* the forward-difference Jacobian (:func:`fd_steps`, :func:`fd_points`, :func:`fd_jacobian`):
  a step ``h`` per coordinate, taken downwards where ``u + h`` would pass the upper bound, or
  where it would break a check that ``u`` passes and ``u - h`` does not (``breaks``: a
  function of two points the caller gives, such as the physics checks decided by a point's
  parameter values); a column the caller finds broken only after its run (a check on the
  simulated responses) may be asked again the other way (:meth:`AskTellLeastSquares.reverse_fd`);
  a run that failed leaves its column at 0;
* the bookkeeping of a request: the points asked, each told point kept as a :class:`Point`,
  the evaluations counted, the reason a solver stopped;
* a trial is accepted when it lowers the sum of squares.

How a damped Gauss-Newton step is chosen is the solver's step rule, and each user keeps the
rule its results were made with (a campaign is bound to the calls its method made):

* :class:`~hmcore.calibration.trust_region_reflective.TrustRegionReflective` (the ``lm``
  method): scipy's trust-region reflective algorithm, ``scipy.optimize.least_squares(
  method="trf", x_scale=1.0)``, as a state machine: one trial point per request, the radius
  of a trust region as the damping, reflection at the bounds, a new finite-difference
  Jacobian at every accepted point (or, with ``refresh``, Broyden's update and a few columns
  anew). Its module computes with scipy's helpers (whose import
  takes a second), so that the recalibrations, which need only numpy, do not load them.
* :class:`LevenbergMarquardt` (the recalibrations): Marquardt's damping ``lam * diag(J'J)``
  with several damping values tried together, an active set at the bounds and projection
  onto the box, and Broyden rank-one updates of the Jacobian in place of new finite
  differences.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass
class Point:
    """A simulated point: coordinates, residual vector (None if the run failed), payload."""

    u: np.ndarray
    r: np.ndarray | None
    payload: Any = None

    @property
    def ssr(self) -> float:
        return float(self.r @ self.r) if self.r is not None else math.inf


# ----------------------------------------------------------------------------- Jacobian
def fd_steps(u: np.ndarray, h: float, upper: np.ndarray | float) -> np.ndarray:
    """The forward-difference step of each coordinate: ``h``, or ``-h`` where ``u + h`` would
    pass ``upper``."""
    return np.where(u + h <= upper, h, -h)


def fd_points(u: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """The finite-difference points at ``u``: row ``i`` is ``u`` with ``steps[i]`` added to
    coordinate ``i``."""
    return u[None, :] + np.diag(steps)


def fd_jacobian(r0: np.ndarray, residuals: list[np.ndarray | None], steps: np.ndarray
                ) -> np.ndarray:
    """The forward-difference Jacobian at a point of residuals ``r0``, from the residuals at
    its :func:`fd_points` (in order): a failed run, or a residual vector of another length,
    leaves its column at 0."""
    J = np.zeros((r0.size, steps.size))
    for k, r in enumerate(residuals):
        if r is not None and r.size == r0.size:
            J[:, k] = (r - r0) / steps[k]
    return J


# ----------------------------------------------------------------------------- ask/tell
class AskTellLeastSquares:
    """The requests of a bounded least-squares solver: the points asked and not yet told
    (each with its kind, ``"start"``, ``"fd"`` or ``"trial"``, and a tag), the told points,
    the evaluations counted, and why the solver stopped."""

    def __init__(self, n: int, fd_step: float, lower: np.ndarray | None,
                 upper: np.ndarray | None,
                 breaks: Callable[[np.ndarray, np.ndarray], bool] | None = None):
        self.fd_step = fd_step
        self.lower = np.full(n, -1.0) if lower is None else np.asarray(lower, float)
        self.upper = np.full(n, 1.0) if upper is None else np.asarray(upper, float)
        self.breaks = breaks
        """``breaks(v, u)``: whether point ``v`` breaks a check that point ``u`` passes (None:
        no checks known before a run)."""
        self.n_evaluations = 0
        self.evaluated: list[Point] = []
        self.done = False
        self.reason = ""
        self._pending: list[tuple[str, np.ndarray, Any]] = []
        self._fd_base: np.ndarray | None = None  # the point of the last finite differences

    def fd_steps(self, u: np.ndarray) -> np.ndarray:
        """The finite-difference step of each coordinate at ``u``: :func:`fd_steps`, each
        turned the other way where the step would break a check that ``u`` passes and the
        other way stays in the box and breaks none (else kept: nothing better is known)."""
        steps = fd_steps(u, self.fd_step, self.upper)
        if self.breaks is None:
            return steps
        for i, v in enumerate(fd_points(u, steps)):
            if self.breaks(v, u):
                w = u.copy()
                w[i] -= steps[i]
                if self.lower[i] <= w[i] <= self.upper[i] and not self.breaks(w, u):
                    steps[i] = -steps[i]
        return steps

    def fd_points(self, u: np.ndarray) -> np.ndarray:
        """The finite-difference points this solver asks at ``u`` (one row per coordinate)."""
        return fd_points(u, self.fd_steps(u))

    def _fd_requests(self, u: np.ndarray, columns: list[int] | None = None
                     ) -> list[tuple[str, np.ndarray, Any]]:
        """The finite-difference requests at ``u``: every column, or those of ``columns``."""
        self._fd_base = u.copy()
        steps = self.fd_steps(u)
        requests = [("fd", v, (i, float(h))) for i, (v, h) in enumerate(zip(fd_points(u, steps),
                                                                             steps))]
        return requests if columns is None else [requests[i] for i in columns]

    def reverse_fd(self, i: int) -> np.ndarray | None:
        """Turn the pending finite-difference run of coordinate ``i`` the other way (its run
        came back broken by a check its base passes, say) and return the new point; None,
        and nothing changed, when the other way leaves the box or breaks a check."""
        u = self._fd_base
        for k, (kind, _, tag) in enumerate(self._pending):
            if kind == "fd" and tag[0] == i:
                h = tag[1]
                w = u.copy()
                w[i] -= h
                if not self.lower[i] <= w[i] <= self.upper[i] or (
                        self.breaks is not None and self.breaks(w, u)):
                    return None
                self._pending[k] = ("fd", w, (i, -h))
                return w
        raise ValueError(f"no finite-difference run of coordinate {i} is pending")

    def _receive(self, results: list[tuple[np.ndarray | None, Any]]
                 ) -> list[tuple[tuple[str, np.ndarray, Any], Point]]:
        """The pending requests paired with their told points (kept in ``evaluated``)."""
        if len(results) != len(self._pending):
            raise ValueError(f"expected {len(self._pending)} results, got {len(results)}")
        pending, self._pending = self._pending, []
        self.n_evaluations += len(results)
        pts = [Point(p[1], None if r is None else np.asarray(r, float), payload)
               for p, (r, payload) in zip(pending, results)]
        self.evaluated.extend(pts)
        return list(zip(pending, pts))

    @staticmethod
    def _jacobian(r0: np.ndarray, received) -> np.ndarray:
        """The finite-difference Jacobian from the ``"fd"`` requests among ``received``."""
        fd = [(tag, q) for (kind, _, tag), q in received if kind == "fd"]
        steps = np.array([h for (_, h), _ in fd])
        return fd_jacobian(r0, [q.r for _, q in fd], steps)

    def _finish(self, reason: str) -> list:
        self.done = True
        self.reason = reason
        return []


# ----------------------------------------------------------------------------- Marquardt
@dataclass
class LMSettings:
    fd_step: float = 0.1
    """Finite-difference step in scaled coordinates (0.1 = 5 % of a parameter's range)."""
    max_iter: int = 8
    max_evaluations: int = 60
    trials: int = 2
    """Trial steps per iteration (damping lam, lam * 10, ...): simulated together."""
    ftol: float = 2e-3
    """Stop when an accepted step lowers the SSR by less than this fraction."""
    atol: float = 1.0
    """... or by less than this (chi-square units): below noise."""
    lam0: float = 1e-2
    max_refresh: int = 1
    """Fresh finite-difference Jacobians allowed after Broyden steps stall."""


@dataclass
class LMHistory:
    iteration: int
    ssr: float
    accepted: bool
    lam: float
    n_evaluations: int
    note: str = ""


class LevenbergMarquardt(AskTellLeastSquares):
    """Bounded Levenberg-Marquardt on ``r(u)``, warm-startable, for several minimisations run
    in lockstep.

    ``ask()`` returns the start point and its finite differences (one batch), a Jacobian's
    points, or trial steps for several damping values ``lam, 10 lam, ...`` (the step solves
    ``(J'J + lam diag(J'J)) s = -J'r`` over the free coordinates, projected onto the box). A
    coordinate at a bound whose gradient points outwards is held. After the first Jacobian
    every simulated trial updates it by Broyden's rank-one formula (no new finite differences
    unless progress stalls), which keeps a recalibration to a handful of runs."""

    def __init__(self, u0: np.ndarray, settings: LMSettings | None = None, *,
                 start: Point | None = None, jacobian: np.ndarray | None = None,
                 lower: np.ndarray | None = None, upper: np.ndarray | None = None,
                 label: str = ""):
        self.s = settings or LMSettings()
        self.u = np.clip(np.asarray(u0, float), -1.0, 1.0)
        super().__init__(self.u.size, self.s.fd_step, lower, upper)
        self.label = label
        self.best: Point | None = start
        self.J = None if jacobian is None else np.array(jacobian, float)
        self.J_fd: np.ndarray | None = None
        """The last finite-difference Jacobian (at ``u_fd``), kept apart from Broyden's."""
        self.u_fd: np.ndarray | None = None
        self.jacobian_is_fresh = False
        self.lam = self.s.lam0
        self.iteration = 0
        self.refreshes = 0
        self.failures_in_row = 0
        self.history: list[LMHistory] = []
        if self.best is not None and self.best.r is None:
            raise ValueError("the start point of a recalibration must have a residual vector")

    # ------------------------------------------------------------------ ask
    @property
    def stepping(self) -> bool:
        """True when the next points are trial steps (start point and Jacobian known)."""
        return not self.done and self.best is not None and self.J is not None

    def ask(self, extra_trials: int = 0) -> list[np.ndarray]:
        """Points to simulate next; ``extra_trials`` more damping values when stepping."""
        if self.done:
            return []
        if self.n_evaluations >= self.s.max_evaluations:
            return self._finish("evaluation budget spent")
        if self.best is None:  # the start point and its finite differences in one batch
            self._pending = [("start", self.u.copy(), None)]
            if self.J is None:
                self._pending += self._fd_requests(self.u)
        elif self.J is None:
            self._pending = self._fd_requests(self.best.u)
        else:
            if self.iteration >= self.s.max_iter:
                return self._finish("iteration limit")
            trials = self._trial_points(self.s.trials + extra_trials)
            if not trials:
                return self._finish("no descent direction inside the bounds (converged)")
            self._pending = trials
        return [p[1] for p in self._pending]

    def _trial_points(self, n_trials: int) -> list[tuple[str, np.ndarray, Any]]:
        J, r, u = self.J, self.best.r, self.best.u
        g = J.T @ r
        A = J.T @ J
        eps = 1e-9
        held = ((u <= self.lower + eps) & (g > 0)) | ((u >= self.upper - eps) & (g < 0))
        free = ~held
        if not free.any():
            return []
        Af, gf = A[np.ix_(free, free)], g[free]
        d = np.diag(Af).copy()
        d = np.maximum(d, 1e-6 * max(float(d.max()), 1e-12))
        pts, seen = [], []
        for k in range(n_trials):
            lam = self.lam * (10.0 ** k)
            try:
                step = np.linalg.solve(Af + lam * np.diag(d), -gf)
            except np.linalg.LinAlgError:
                continue
            v = u.copy()
            v[free] = np.clip(u[free] + step, self.lower[free], self.upper[free])
            if np.max(np.abs(v - u)) < 1e-6 or any(np.allclose(v, s, atol=1e-6) for s in seen):
                continue
            seen.append(v)
            pts.append(("trial", v, lam))
        return pts

    # ------------------------------------------------------------------ tell
    def tell(self, results: list[tuple[np.ndarray | None, Any]]) -> None:
        received = self._receive(results)
        for (kind, _, _), p in received:
            if kind != "start":
                continue
            if p.r is None:
                self._finish("the start point failed to simulate")
                return
            self.best = p
            self.history.append(LMHistory(0, self.best.ssr, True, self.lam, self.n_evaluations,
                                          "start"))
        if any(kind == "fd" for (kind, _, _), _ in received):
            self.J = self._jacobian(self.best.r, received)
            self.jacobian_is_fresh = True
            self.J_fd, self.u_fd = self.J.copy(), self.best.u.copy()
        trials = [(req, p) for req, p in received if req[0] == "trial"]
        if trials:
            self._after_trials([req for req, _ in trials], [p for _, p in trials])

    def _after_trials(self, pending, pts: list[Point]) -> None:
        self.iteration += 1
        ok = [(p, lam) for (_, _, lam), p in zip(pending, pts) if p.r is not None]
        before = self.best.ssr
        for p, _ in ok:  # every simulated step teaches the Jacobian something (Broyden)
            self._broyden(p)
        if ok:
            p, lam = min(ok, key=lambda t: t[0].ssr)
        if ok and p.ssr < before:
            gain = before - p.ssr
            self.best = p
            self.u = p.u.copy()
            self.lam = max(lam / 10.0, 1e-7)
            self.failures_in_row = 0
            self.history.append(LMHistory(self.iteration, p.ssr, True, lam, self.n_evaluations))
            if gain < self.s.ftol * before or gain < self.s.atol:
                self._finish("converged (the last step gained less than the tolerance)")
            return
        self.failures_in_row += 1
        self.lam *= 10.0 ** (self.s.trials + 1)
        self.history.append(LMHistory(self.iteration, before, False, self.lam,
                                      self.n_evaluations, "no trial improved"))
        if self.failures_in_row >= 2 and not self.jacobian_is_fresh:
            if self.refreshes < self.s.max_refresh:
                self.refreshes += 1
                self.J = None  # recompute by finite differences at the best point
                self.lam = self.s.lam0
                self.failures_in_row = 0
                return
            self._finish("no further progress")
        elif self.failures_in_row >= 3 or self.lam > 1e8:
            self._finish("no further progress")

    def _broyden(self, p: Point) -> None:
        du = p.u - self.best.u
        nn = float(du @ du)
        if nn < 1e-12:
            return
        dr = p.r - self.best.r
        self.J = self.J + np.outer(dr - self.J @ du, du) / nn
        self.jacobian_is_fresh = False

    def trim(self, n: int) -> list[np.ndarray]:
        """Keep the first ``n`` of the points just asked for, when they are all trial steps
        (fewer damping values this iteration); otherwise (a start point or a Jacobian cannot
        be cut short) or when ``n < 1``, ask for nothing and stop: "simulation budget spent".
        Returns the points still to simulate."""
        if n >= len(self._pending):
            return [p[1] for p in self._pending]
        if n >= 1 and all(p[0] == "trial" for p in self._pending):
            self._pending = self._pending[:n]
            return [p[1] for p in self._pending]
        self._pending = []
        return self._finish("simulation budget spent")
