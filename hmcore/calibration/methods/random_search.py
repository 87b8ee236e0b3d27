"""Uniform random search: the simplest proposer, a baseline and a fast test double."""

from __future__ import annotations

import numpy as np

from hmcore.calibration.methods.base import Sampler


class RandomProposer(Sampler):
    name = "random"

    def __init__(self, dim: int, seed: int):
        super().__init__(dim)
        self.rng = np.random.default_rng(seed)

    def _points(self, n: int) -> np.ndarray:
        return np.stack([self.rng.uniform(-1, 1, self.dim) for _ in range(n)])
