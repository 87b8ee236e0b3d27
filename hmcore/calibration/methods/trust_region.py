"""A trust region around the incumbent (the best call so far), in action space [-1, 1]^d.

The side length grows after successes and shrinks after failures, as in TuRBO (Eriksson et al.
2019, "Scalable global optimization via local Bayesian optimization"): a batch that improves
the incumbent is a success; ``failure_tolerance`` batches in a row without one halve the side;
``success_tolerance`` in a row double it (capped at ``side_max``). Below ``side_min`` the region
restarts at ``side_init`` around the incumbent. Pure state, no learning, no simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrustRegionSettings:
    side_init: float = 0.8     # side length, in action units (the box is 2 wide)
    side_min: float = 0.02
    side_max: float = 2.0
    success_tolerance: int = 2
    failure_batches: float = 4.0  # failures tolerated: ceil(max(this, dim) / batch size)
    improvement: float = 1e-3  # a relative gain below this is no success


class TrustRegion:
    def __init__(self, dim: int, settings: TrustRegionSettings | None = None):
        self.dim = dim
        self.settings = settings or TrustRegionSettings()
        self.side = self.settings.side_init
        self.centre: np.ndarray | None = None
        self.best = math.inf
        self.successes = 0
        self.failures = 0
        self.restarts = 0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The region's box, clipped to [-1, 1] (the whole box before any call is told)."""
        if self.centre is None:
            return -np.ones(self.dim), np.ones(self.dim)
        half = self.side / 2.0
        return np.clip(self.centre - half, -1, 1), np.clip(self.centre + half, -1, 1)

    def update(self, actions: np.ndarray, costs: np.ndarray) -> None:
        """One told batch: ``costs`` (lower is better; inf for a failed run)."""
        s = self.settings
        k = int(np.argmin(costs))
        improved = costs[k] < self.best - s.improvement * abs(self.best) \
            if math.isfinite(self.best) else math.isfinite(costs[k])
        if costs[k] < self.best:
            self.best, self.centre = float(costs[k]), np.asarray(actions[k], float)
        if self.centre is None:  # nothing scored yet: stay on the whole box
            return
        if improved:
            self.successes, self.failures = self.successes + 1, 0
        else:
            self.successes, self.failures = 0, self.failures + 1
        tolerance = math.ceil(max(s.failure_batches, self.dim) / max(len(costs), 1))
        if self.successes >= s.success_tolerance:
            self.side, self.successes = min(2.0 * self.side, s.side_max), 0
        elif self.failures >= tolerance:
            self.side, self.failures = self.side / 2.0, 0
        if self.side < s.side_min:
            self.side, self.restarts = s.side_init, self.restarts + 1
