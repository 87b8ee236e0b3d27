"""Scrambled Sobol' points (scipy.stats.qmc): space-filling, no learning; a baseline."""

from __future__ import annotations

import warnings

import numpy as np
from scipy.stats import qmc

from hmcore.calibration.methods.base import Sampler


class SobolProposer(Sampler):
    name = "sobol"

    def __init__(self, dim: int, seed: int):
        super().__init__(dim)
        self.sampler = qmc.Sobol(dim, scramble=True, seed=np.random.default_rng(seed))

    def _points(self, n: int) -> np.ndarray:
        with warnings.catch_warnings():  # scipy warns when n is not a power of 2; the sequence
            warnings.simplefilter("ignore", UserWarning)  # is the same sequence all the same
            return self.sampler.random(n) * 2.0 - 1.0
