"""Warm-started local recalibration: bounded Levenberg-Marquardt on whitened residuals.

Parameters live in scaled coordinates ``u`` in ``[-1, 1]`` per parameter: linear in the value
for skins, linear in log(value) for multipliers, item multipliers and relperm exponents, so
one finite-difference step means the same relative change everywhere (:class:`Coordinates`,
the parameters' :class:`~hmcore.model.parameters.Scaling` with every factor log-scaled).

The minimiser is the ask/tell :class:`~hmcore.calibration.least_squares.LevenbergMarquardt`
(with :class:`LMSettings`, :class:`Point`; imported from here too): ``ask()`` returns the
points to simulate next, ``tell()`` takes their residual vectors (None for a failed run).
Nothing runs a simulator, so several minimisations run in lockstep and share one batch of
parallel simulations (:func:`run_lockstep`, the recalibration's driver).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

from hmcore.calibration.least_squares import LevenbergMarquardt, LMHistory, LMSettings, Point
from hmcore.model.parameters import Parameter, Scaling

LOG_KINDS = ("multiply", "item_multiply", "relperm", "wpimult", "table_multiply")
"""Kinds whose value is a factor: scaled in log(value) here (a relperm end-point shift is not)."""

__all__ = ["LOG_KINDS", "Coordinates", "LMHistory", "LMSettings", "LevenbergMarquardt", "Point",
           "log_scaled", "run_lockstep"]


def log_scaled(p: Parameter) -> bool:
    """Whether the recalibration scales ``p`` in log(value): when its case says so, and for
    every factor (:data:`LOG_KINDS`), so that one finite-difference step is the same relative
    change for every factor."""
    return p.log or (p.kind in LOG_KINDS and p.mode != "endpoint")  # a shift: linear


class Coordinates:
    """Physical values <-> scaled coordinates ``u`` in [-1, 1] (log scale for factors): the
    :class:`~hmcore.model.parameters.Scaling` of the parameters, each made log-scaled where
    :func:`log_scaled` says so."""

    def __init__(self, parameters: list[Parameter] | tuple[Parameter, ...]):
        self.parameters = tuple(parameters)
        self.names = [p.name for p in self.parameters]
        self.scaling = Scaling.of([p.model_copy(update={"log": log_scaled(p)})
                                   for p in self.parameters])
        self.log = self.scaling.log

    @property
    def dim(self) -> int:
        return len(self.parameters)

    def to_u(self, values: dict[str, float]) -> np.ndarray:
        return self.scaling.to_scaled([float(values[n]) for n in self.names])

    def to_values(self, u: np.ndarray) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, self.scaling.to_values(u))}


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
