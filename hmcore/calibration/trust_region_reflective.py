"""scipy's trust-region reflective least squares as an ask/tell solver (the step rule of the
``lm`` calibration method).

:class:`TrustRegionReflective` is ``scipy.optimize.least_squares(fun, x0, jac, bounds,
method="trf", x_scale=1.0)`` (linear loss, exact trust-region subproblem by SVD, default
tolerances) turned inside out: instead of calling ``fun`` and ``jac`` it asks for the points
and is told their residuals, so that a caller can batch, replay and budget the simulations.
The algorithm is scipy's ``trf_bounds`` step for step, with scipy's own helpers for the
arithmetic (``scipy.optimize._lsq``, private to scipy: ``tests/test_least_squares.py`` checks
that this class proposes the very points ``least_squares`` evaluates), and ``jac`` is the
forward difference of :mod:`hmcore.calibration.least_squares`:

1. the start point (made strictly feasible, as scipy does), then its Jacobian;
2. at the current point: the Coleman-Li scaling of the bounds, the SVD of the scaled Jacobian,
   a step inside the trust region (reflected at a bound it would cross, or along the scaled
   gradient, whichever the quadratic model likes best), kept strictly inside the box;
3. a trial point per request: the radius is updated from the ratio of actual to predicted
   reduction; a worse trial is followed by a shorter one from the same point, a better one is
   accepted and the Jacobian is computed there (also when a tolerance then ends the descent,
   as scipy does);
4. it ends when the scaled gradient, the cost reduction or the step falls below its
   tolerance (``status`` 1, 2, 3 or 4 as scipy's), or after ``max_nfev`` residual
   evaluations (``status`` 0; Jacobian runs are not counted, as in scipy).

A failed run (a residual vector of None) at the start or at a trial ends the descent
(``failed``); in a Jacobian its column is 0. Non-finite residuals at a trial shrink the
radius, as in scipy.

With ``breaks`` (whether a point breaks a check that another passes, decided before any run:
:class:`~hmcore.calibration.least_squares.AskTellLeastSquares`), a check's boundary is handled
like a bound: a finite-difference step that would cross it goes the other way; where a check
breaks within a finite-difference step of the current point along a coordinate, that edge is
the coordinate's bound for the iteration (:meth:`TrustRegionReflective._edges`: the
Coleman-Li scaling then slows the steps towards it and trial steps reflect off it, so a
descent slides along the edge instead of stopping at it); and a trial step that would still
cross a check from the current point (an edge across the coordinates, further away) is cut
where it reaches the edge (found by bisection on ``breaks``, no run needed), then kept 0.995
of the way as scipy keeps a step inside the box, with the reduction the model predicts for
the shorter step. When the cut step is shorter than :data:`MIN_TRUNCATED_STEP` (the current
point is at the edge in that direction), the trial is not asked at all: it is taken as
non-finite residuals (the radius shrinks to a quarter of the step and another trial is
tried, as scipy does on a point outside ``fun``'s domain), counted in ``skipped``, not in
``nfev``. After :data:`MAX_SKIPPED_IN_ROW` in a row the descent ends (``status`` None,
``reason`` says why). Without ``breaks`` the solver is scipy's, point for point.

With ``refresh`` (a number of columns, ``None`` by default: scipy's rule), an accepted trial is
not followed by a whole new finite-difference Jacobian but by Broyden's rank-one (secant)
update along the step (Broyden, 1965, Math. Comp. 19: 577-593; Dennis and Schnabel, 1996,
*Numerical Methods for Unconstrained Optimization and Nonlinear Equations*, SIAM, section
8.1), with ``refresh`` of its columns then computed anew by finite differences at the new
point, in turn (:meth:`TrustRegionReflective.refresh_columns`), so that every column is a
finite difference again every ``n / refresh`` accepted steps. A trial rejected while some
columns are secant estimates is followed by finite differences of those columns at the
current point before the next (shorter) trial: a rejection is then never the Jacobian's
fault. An iteration costs a trial and ``refresh`` runs instead of a trial and ``n`` runs.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.linalg import norm
from scipy.linalg import svd
from scipy.optimize._lsq.common import (
    CL_scaling_vector,
    check_termination,
    compute_grad,
    evaluate_quadratic,
    in_bounds,
    make_strictly_feasible,
    solve_lsq_trust_region,
    update_tr_radius,
)
from scipy.optimize._lsq.trf import select_step

from hmcore.calibration.least_squares import AskTellLeastSquares

STATUS = {0: "the residual evaluations allowed are spent",
          1: "the scaled gradient is below gtol",
          2: "the cost reduction is below ftol",
          3: "the step is below xtol",
          4: "the cost reduction and the step are below ftol and xtol"}
"""Why a descent ended, by scipy's status number."""
EDGE_BISECTIONS = 20
"""Bisections that find where a trial step reaches a check's edge (to a millionth of it)."""
EDGE_MARGIN = 1e-10
"""The least distance from ``x`` of a bound at a check's edge."""
MIN_TRUNCATED_STEP = 1e-4
"""A trial step cut at a check's edge is tried when at least this long (scaled units); a
shorter one means the current point is at the edge in that direction: the radius shrinks."""
MAX_SKIPPED_IN_ROW = 40
"""Trial points crossing a check, in a row, before a descent ends: each shrinks the radius to
a quarter, so 40 take it from the box's size to below a float's resolution."""


@dataclass(frozen=True)
class _Scaled:
    """The trust-region problem at the current point, in scipy's scaled ("hat") variables:
    the Coleman-Li scaling ``d``, the bound term ``diag_h``, the scaled gradient and Jacobian,
    and the SVD of the augmented Jacobian (``uf = U'f``, ``s``, ``V``)."""

    d: np.ndarray
    diag_h: np.ndarray
    g_h: np.ndarray
    J_h: np.ndarray
    uf: np.ndarray
    s: np.ndarray
    V: np.ndarray
    theta: float  # how far a step may go towards a bound (0.995 of the way, or more)
    lower: np.ndarray  # the bounds of this iteration's trials: the box, or a check's edge
    upper: np.ndarray


@dataclass(frozen=True)
class _Trial:
    """A trial point asked, the step to it, the reduction the model predicts, and (once told)
    its residuals and cost."""

    x_new: np.ndarray
    step: np.ndarray
    step_h: np.ndarray
    predicted: float
    f_new: np.ndarray | None = None
    cost_new: float = math.nan


class TrustRegionReflective(AskTellLeastSquares):
    """Bounded trust-region reflective least squares on ``r(u)`` by ask/tell (see the module
    docstring). ``x``, ``cost`` (half the sum of squares) and ``status`` describe the current
    point, and the result once ``done``."""

    def __init__(self, u0: np.ndarray, fd_step: float, *, lower: np.ndarray | None = None,
                 upper: np.ndarray | None = None, max_nfev: int | None = None,
                 ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8,
                 breaks: Callable[[np.ndarray, np.ndarray], bool] | None = None,
                 refresh: int | None = None):
        x0 = np.atleast_1d(np.asarray(u0)).astype(float)
        super().__init__(x0.size, fd_step, lower, upper, breaks)
        if refresh is not None and not 1 <= refresh <= x0.size:
            raise ValueError(f"refresh must be None or between 1 and {x0.size} columns, "
                             f"got {refresh}")
        self.refresh = refresh
        """Columns computed anew after a secant update (None: a whole Jacobian, scipy's)."""
        self.fresh = np.zeros(x0.size, bool)
        """Which columns of ``J`` are finite differences at ``x`` (the others: secant)."""
        self._turn = 0  # the first column of the next refresh
        self._completing = False  # the columns asked by complete(): the end once told
        if not in_bounds(x0, self.lower, self.upper):
            raise ValueError(f"the start point {x0.tolist()} is outside the bounds")
        if max_nfev is not None and max_nfev <= 0:
            raise ValueError(f"max_nfev must be None or positive, got {max_nfev}")
        self.x = make_strictly_feasible(x0, self.lower, self.upper)
        self.max_nfev = max_nfev if max_nfev is not None else 100 * x0.size
        self.ftol, self.xtol, self.gtol = ftol, xtol, gtol
        self.f: np.ndarray | None = None
        self.J: np.ndarray | None = None
        self.g: np.ndarray | None = None
        self.cost = math.nan
        self.nfev = 0
        self.skipped = 0  # trial points not asked: they cross a check the current point passes
        self._skipped_in_row = 0
        self.iteration = 0
        self.status: int | None = None
        self.failed = False
        self.Delta: float | None = None  # trust-region radius (scaled space)
        self.alpha = 0.0  # Levenberg-Marquardt parameter of the trust-region subproblem
        self.actual_reduction = -1.0  # of the last trial's cost
        self._scaled: _Scaled | None = None
        self._trial: _Trial | None = None
        self._pending = [("start", self.x.copy(), None)]

    # ------------------------------------------------------------------ ask
    def ask(self) -> list[np.ndarray]:
        """The points to simulate next: one (the start or a trial) or a Jacobian's."""
        return [] if self.done else [p[1] for p in self._pending]

    @property
    def jacobian_asked(self) -> bool:
        """True when the points asked are the finite differences at ``x``."""
        return bool(self._pending) and self._pending[0][0] == "fd"

    @property
    def columns_asked(self) -> list[int]:
        """The coordinates of the finite differences asked, in the order of :meth:`ask`."""
        return [tag[0] for kind, _, tag in self._pending if kind == "fd"]

    @property
    def secant_columns(self) -> list[int]:
        """The columns of ``J`` that are not finite differences at ``x``."""
        return [int(k) for k in np.flatnonzero(~self.fresh)]

    def refresh_columns(self, k: int) -> list[int]:
        """The first ``k`` columns this solver asks at a point it accepts next: the whole
        Jacobian's first ``k`` without ``refresh`` (or before the first Jacobian), else the
        next ``k`` in turn (what a caller may simulate beside a trial, ahead of the answer)."""
        k = max(0, min(k, self.x.size))
        if self.refresh is None or self.J is None:
            return list(range(k))
        return [(self._turn + i) % self.x.size for i in range(k)]

    # ------------------------------------------------------------------ tell
    def tell(self, results: list[tuple[np.ndarray | None, Any]]) -> None:
        received = self._receive(results)
        (kind, _, _), p = received[0]
        if kind == "fd":
            columns = [tag[0] for (k, _, tag), _ in received if k == "fd"]
            if self.J is None or len(columns) == self.x.size:
                self.J = self._jacobian(self.f, received)
            else:  # some columns anew, the others kept (secant estimates)
                self.J[:, columns] = self._jacobian(self.f, received)
            self.fresh[columns] = True
            self.g = compute_grad(self.J, self.f)
            if self._completing:
                self._completing = False
                self.done = True
                return
            if self.Delta is None:
                self._begin()
            else:
                self.iteration += 1
            self._iterate()
        elif p.r is None:
            self.failed = True
            self._finish(f"the {kind} point failed to simulate")
        elif kind == "start":
            self.f, self.nfev = p.r, 1
            self.cost = 0.5 * np.dot(self.f, self.f)
            self._pending = self._fd_requests(self.x)
        else:
            self._told_trial(p.r)

    def complete(self) -> bool:
        """Ask anew, at ``x``, the columns of ``J`` that are secant estimates (or were never
        told there), the solver ending once they are told: a whole finite-difference
        Jacobian at the point a descent ended on. False, nothing asked, when there are none
        or no Jacobian was ever computed (a failed start)."""
        if self.J is None or self.failed or self.fresh.all():
            return False
        self._pending = self._fd_requests(self.x, self.secant_columns)
        self._completing = True
        self.done = False
        return True

    # ------------------------------------------------------------------ the algorithm
    def _begin(self) -> None:
        """The initial radius, once the start point and its Jacobian are known."""
        if not np.all(np.isfinite(self.f)):
            raise ValueError("Residuals are not finite in the initial point.")
        v, _ = CL_scaling_vector(self.x, self.g, self.lower, self.upper)
        self.Delta = norm(self.x / v**0.5)
        if self.Delta == 0:
            self.Delta = 1.0

    def _iterate(self) -> None:
        """An outer iteration at the current point: stop, or prepare the scaled trust-region
        problem and ask for the first trial."""
        x, g, f, J = self.x, self.g, self.f, self.J
        lower, upper = self._edges()
        v, dv = CL_scaling_vector(x, g, lower, upper)
        g_norm = norm(g * v, ord=np.inf)
        if g_norm < self.gtol:
            self.status = 1
        if self.status is not None or self.nfev == self.max_nfev:
            self.status = self.status or 0
            self._finish(STATUS[self.status])
            return
        m, n = J.shape
        d = v**0.5
        diag_h = g * dv
        f_augmented = np.zeros(m + n)
        f_augmented[:m] = f
        J_augmented = np.empty((m + n, n))
        J_augmented[:m] = J * d
        J_augmented[m:] = np.diag(diag_h**0.5)
        U, s, V = svd(J_augmented, full_matrices=False)
        self._scaled = _Scaled(d, diag_h, d * g, J_augmented[:m], U.T.dot(f_augmented), s, V.T,
                               max(0.995, 1 - g_norm), lower, upper)
        self.actual_reduction = -1
        self._next_trial()

    def _next_trial(self) -> None:
        """Ask for a trial point from the current one, or end the outer iteration; a trial
        step that crosses a check the current point passes is cut at the check's edge, or,
        when that leaves too short a step, taken as non-finite and not asked (see the module
        docstring)."""
        while True:
            if not (self.actual_reduction <= 0 and self.nfev < self.max_nfev):
                self._end_iteration()
                return
            h = self._scaled
            m, n = h.J_h.shape
            p_h, self.alpha, _ = solve_lsq_trust_region(n, m, h.uf, h.s, h.V, self.Delta,
                                                        initial_alpha=self.alpha)
            p = h.d * p_h
            step, step_h, predicted = select_step(self.x, h.J_h, h.diag_h, h.g_h, p, p_h, h.d,
                                                  self.Delta, h.lower, h.upper, h.theta)
            x_new = make_strictly_feasible(self.x + step, h.lower, h.upper, rstep=0)
            if self.breaks is not None and self.breaks(x_new, self.x):
                t = self._inside(step) * h.theta
                if t * norm(step) >= MIN_TRUNCATED_STEP:  # up to the check's edge, as a bound
                    step, step_h = t * step, t * step_h
                    predicted = -evaluate_quadratic(h.J_h, h.g_h, step_h, diag=h.diag_h)
                    x_new = make_strictly_feasible(self.x + step, h.lower, h.upper, rstep=0)
            if self.breaks is None or not self.breaks(x_new, self.x):
                self._skipped_in_row = 0
                self._trial = _Trial(x_new, step, step_h, predicted)
                self._pending = [("trial", x_new.copy(), None)]
                return
            self.skipped += 1
            self._skipped_in_row += 1
            if self._skipped_in_row >= MAX_SKIPPED_IN_ROW:
                self._finish(f"{MAX_SKIPPED_IN_ROW} trial points in a row cross a check the "
                             "current point passes")
                return
            self.Delta = 0.25 * norm(step_h)  # as scipy on non-finite residuals

    def _edges(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounds of this iteration's trials: the box, tightened along each coordinate to
        where a check that ``x`` passes breaks within a finite-difference step of ``x`` (the
        edge found by bisection; at least :data:`EDGE_MARGIN` away, so that ``x`` stays
        strictly inside, as the trust-region scaling needs)."""
        lower, upper = self.lower.copy(), self.upper.copy()
        if self.breaks is None:
            return lower, upper
        for i in range(self.x.size):
            for sign in (1.0, -1.0):
                step = np.zeros_like(self.x)
                step[i] = sign * self.fd_step
                x_far = make_strictly_feasible(self.x + step, self.lower, self.upper, rstep=0)
                if not self.breaks(x_far, self.x):
                    continue
                edge = self.x[i] + sign * max(self._inside(step) * self.fd_step, EDGE_MARGIN)
                if sign > 0:
                    upper[i] = min(upper[i], edge)
                else:
                    lower[i] = max(lower[i], edge)
        return lower, upper

    def _inside(self, step: np.ndarray) -> float:
        """How far along ``step`` from ``x`` the points still pass the checks ``x`` passes:
        the largest such fraction found by :data:`EDGE_BISECTIONS` bisections (0 when none)."""
        lo, hi = 0.0, 1.0
        for _ in range(EDGE_BISECTIONS):
            mid = 0.5 * (lo + hi)
            x_mid = make_strictly_feasible(self.x + mid * step, self.lower, self.upper, rstep=0)
            if self.breaks(x_mid, self.x):
                hi = mid
            else:
                lo = mid
        return lo

    def _told_trial(self, f_new: np.ndarray) -> None:
        t = self._trial
        self.nfev += 1
        step_h_norm = norm(t.step_h)
        if not np.all(np.isfinite(f_new)):
            self.Delta = 0.25 * step_h_norm
            self._next_trial()
            return
        cost_new = 0.5 * np.dot(f_new, f_new)
        self._trial = dataclasses.replace(t, f_new=f_new, cost_new=cost_new)
        self.actual_reduction = self.cost - cost_new
        Delta_new, ratio = update_tr_radius(self.Delta, self.actual_reduction, t.predicted,
                                            step_h_norm, step_h_norm > 0.95 * self.Delta)
        self.status = check_termination(self.actual_reduction, self.cost, norm(t.step),
                                        norm(self.x), ratio, self.ftol, self.xtol)
        if self.status is not None:
            self._end_iteration()
            return
        self.alpha *= self.Delta / Delta_new
        self.Delta = Delta_new
        if (self.refresh is not None and self.actual_reduction <= 0 and not self.fresh.all()
                and self.nfev < self.max_nfev):  # rejected on secant columns: those anew first
            self._pending = self._fd_requests(self.x, self.secant_columns)
            return
        self._next_trial()

    def _end_iteration(self) -> None:
        """Accept a trial that lowered the cost (and ask for the Jacobian there: all of it,
        or with ``refresh`` the next columns in turn after a secant update), else iterate
        again from the same point (with ``refresh``, after finite differences of the columns
        that are secant estimates: see :meth:`_told_trial`)."""
        if self.actual_reduction > 0:
            t = self._trial
            if self.refresh is not None and self.status is None:
                self._secant(t.x_new - self.x, t.f_new - self.f)
            self.x, self.f, self.cost = t.x_new, t.f_new, t.cost_new
            self.fresh[:] = False
            if self.refresh is None or self.status is not None:
                self._pending = self._fd_requests(self.x)
                return
            columns = self.refresh_columns(self.refresh)
            self._turn = (self._turn + self.refresh) % self.x.size
            self._pending = self._fd_requests(self.x, columns)
            return
        self.iteration += 1
        self._iterate()

    def _secant(self, step: np.ndarray, change: np.ndarray) -> None:
        """Broyden's rank-one update of ``J`` along ``step``, the residuals having changed by
        ``change``: the least change of ``J`` that maps the step to the change."""
        ss = float(step @ step)
        if ss > 0:
            self.J = self.J + np.outer(change - self.J @ step, step) / ss
