"""Warm-started local recalibration: bounded Levenberg-Marquardt on whitened residuals.

Parameters live in scaled coordinates ``u`` in ``[-1, 1]`` per parameter: linear in the value
for skins, linear in log(value) for multipliers, item multipliers and relperm exponents, so
one finite-difference step means the same relative change everywhere (:class:`Coordinates`).

:class:`LevenbergMarquardt` is an ask/tell state machine: ``ask()`` returns the points to
simulate next (the start point, a finite-difference Jacobian's points, or trial steps for
several damping values), ``tell()`` takes their residual vectors (None for a failed run).
Nothing here runs a simulator, so several minimisations can run in lockstep and share one
batch of parallel simulations (:func:`run_lockstep`). After the first Jacobian the
minimiser updates it with Broyden's rank-one formula from every simulated step (no new
finite differences unless progress stalls), which keeps a recalibration to a handful of runs.
Bounds are handled by an active set (a parameter at a bound whose gradient points outwards is
held) and by projection of each trial onto the box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from hmcore.model.parameters import Parameter

LOG_KINDS = ("multiply", "item_multiply", "relperm", "wpimult", "table_multiply")


class Coordinates:
    """Physical values <-> scaled coordinates ``u`` in [-1, 1] (log scale for multipliers)."""

    def __init__(self, parameters: list[Parameter] | tuple[Parameter, ...]):
        self.parameters = tuple(parameters)
        self.names = [p.name for p in self.parameters]
        self.log = np.array([p.kind in LOG_KINDS and p.mode != "endpoint"  # a shift: linear
                             for p in self.parameters], dtype=bool)
        lo = np.array([p.low for p in self.parameters], float)
        hi = np.array([p.high for p in self.parameters], float)
        self._lo, self._hi = lo.copy(), hi.copy()
        self._lo[self.log] = np.log(lo[self.log])
        self._hi[self.log] = np.log(hi[self.log])

    @property
    def dim(self) -> int:
        return len(self.parameters)

    def to_u(self, values: dict[str, float]) -> np.ndarray:
        t = np.array([float(values[n]) for n in self.names])
        t[self.log] = np.log(np.maximum(t[self.log], 1e-300))
        return 2.0 * (t - self._lo) / (self._hi - self._lo) - 1.0

    def to_values(self, u: np.ndarray) -> dict[str, float]:
        u = np.clip(np.asarray(u, float), -1.0, 1.0)
        x = self._lo + (u + 1.0) * 0.5 * (self._hi - self._lo)
        x[self.log] = np.exp(x[self.log])
        return {n: float(v) for n, v in zip(self.names, x)}


@dataclass
class Point:
    """A simulated point: coordinates, residual vector (None if the run failed), payload."""

    u: np.ndarray
    r: np.ndarray | None
    payload: Any = None

    @property
    def ssr(self) -> float:
        return float(self.r @ self.r) if self.r is not None else math.inf


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


class LevenbergMarquardt:
    """Bounded LM on ``r(u)`` driven by ask/tell (see the module docstring)."""

    def __init__(self, u0: np.ndarray, settings: LMSettings | None = None, *,
                 start: Point | None = None, jacobian: np.ndarray | None = None,
                 lower: np.ndarray | None = None, upper: np.ndarray | None = None,
                 label: str = ""):
        self.s = settings or LMSettings()
        self.u = np.clip(np.asarray(u0, float), -1.0, 1.0)
        n = self.u.size
        self.lower = np.full(n, -1.0) if lower is None else np.asarray(lower, float)
        self.upper = np.full(n, 1.0) if upper is None else np.asarray(upper, float)
        self.label = label
        self.best: Point | None = start
        self.J = None if jacobian is None else np.array(jacobian, float)
        self.J_fd: np.ndarray | None = None
        """The last finite-difference Jacobian (at ``u_fd``), kept apart from Broyden's."""
        self.u_fd: np.ndarray | None = None
        self.jacobian_is_fresh = False
        self.lam = self.s.lam0
        self.iteration = 0
        self.n_evaluations = 0
        self.refreshes = 0
        self.failures_in_row = 0
        self.history: list[LMHistory] = []
        self.done = False
        self.reason = ""
        self.evaluated: list[Point] = []
        self._pending: list[tuple[str, np.ndarray, Any]] = []
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
                self._pending += self._fd_points(self.u)
        elif self.J is None:
            self._pending = self._fd_points(self.best.u)
        else:
            if self.iteration >= self.s.max_iter:
                return self._finish("iteration limit")
            trials = self._trial_points(self.s.trials + extra_trials)
            if not trials:
                return self._finish("no descent direction inside the bounds (converged)")
            self._pending = trials
        return [p[1] for p in self._pending]

    def _fd_points(self, u: np.ndarray) -> list[tuple[str, np.ndarray, Any]]:
        pts = []
        for i in range(u.size):
            h = self.s.fd_step if u[i] + self.s.fd_step <= self.upper[i] else -self.s.fd_step
            v = u.copy()
            v[i] += h
            pts.append(("fd", v, (i, h)))
        return pts

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
        if len(results) != len(self._pending):
            raise ValueError(f"expected {len(self._pending)} results, got {len(results)}")
        pending, self._pending = self._pending, []
        self.n_evaluations += len(results)
        pts = [Point(p[1], None if r is None else np.asarray(r, float), payload)
               for p, (r, payload) in zip(pending, results)]
        self.evaluated.extend(pts)
        kinds = [p[0] for p in pending]
        if "start" in kinds:
            k = kinds.index("start")
            if pts[k].r is None:
                self._finish("the start point failed to simulate")
                return
            self.best = pts[k]
            self.history.append(LMHistory(0, self.best.ssr, True, self.lam, self.n_evaluations,
                                          "start"))
        fd = [(p, q) for p, q in zip(pending, pts) if p[0] == "fd"]
        if fd:
            J = np.zeros((self.best.r.size, self.u.size))
            for (_, v, (i, h)), q in fd:
                if q.r is not None:
                    J[:, i] = (q.r - self.best.r) / h
            self.J = J
            self.jacobian_is_fresh = True
            self.J_fd, self.u_fd = J.copy(), self.best.u.copy()
        trials = [(p, q) for p, q in zip(pending, pts) if p[0] == "trial"]
        if trials:
            self._after_trials([p for p, _ in trials], [q for _, q in trials])

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

    def _finish(self, reason: str) -> list:
        self.done = True
        self.reason = reason
        return []


def run_lockstep(minimisers: list[LevenbergMarquardt],
                 evaluate: Callable[[list[tuple[int, np.ndarray]]],
                                    list[tuple[np.ndarray | None, Any]]],
                 workers: int = 1, limit: int | None = None) -> int:
    """Drive several minimisers together: each round, every unfinished one asks for its points
    and all points go to ``evaluate`` in one batch (``[(minimiser index, u), ...]``). When the
    batch would leave some of ``workers`` idle, the best minimisers that are stepping get one
    more damping trial each to fill it.

    ``limit`` caps the points evaluated in all (None: no cap): a round that would pass it is
    cut (no filling trials, then fewer trial steps, in minimiser order), and a minimiser whose
    points cannot be cut (a start point, a Jacobian) stops (:meth:`LevenbergMarquardt.trim`).
    Returns the number of points evaluated."""
    spent = 0
    while True:
        asks = {k: m.ask() for k, m in enumerate(minimisers) if not m.done}
        asks = {k: pts for k, pts in asks.items() if pts}
        if not asks:
            return spent
        total = sum(len(p) for p in asks.values())
        deficit = (-total) % max(workers, 1)
        if limit is not None:
            deficit = min(deficit, max(limit - spent - total, 0))
        order = sorted((k for k in asks if minimisers[k].stepping),
                       key=lambda k: minimisers[k].best.ssr)
        for k in order[:deficit]:
            more = minimisers[k].ask(extra_trials=1)
            if more:
                asks[k] = more
        if limit is not None and total > limit - spent:
            room = limit - spent
            for k in list(asks):
                asks[k] = minimisers[k].trim(room)
                room -= len(asks[k])
            asks = {k: pts for k, pts in asks.items() if pts}
            if not asks:
                return spent
        batch = [(k, u) for k, pts in asks.items() for u in pts]
        results = evaluate(batch)
        spent += len(batch)
        pos = 0
        for k, pts in asks.items():
            minimisers[k].tell(results[pos:pos + len(pts)])
            pos += len(pts)
