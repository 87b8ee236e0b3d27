"""Scrambled Sobol' points (scipy.stats.qmc): space-filling, no learning; a baseline."""

from __future__ import annotations

import warnings

import numpy as np
from scipy.stats import qmc

from hmcore.agents.base import Feedback, LaneMemory, Proposal
from hmcore.env import observation


class SobolProposer:
    name = "sobol"
    exploit_last = False  # its recommendation is a point already evaluated

    def __init__(self, dim: int, seed: int):
        self.dim = dim
        self.sampler = qmc.Sobol(dim, scramble=True, seed=np.random.default_rng(seed))
        self.lanes = LaneMemory(dim)
        self._best: tuple[float, np.ndarray] | None = None

    def ask(self, n: int) -> list[Proposal]:
        with warnings.catch_warnings():  # scipy warns when n is not a power of 2; the sequence
            warnings.simplefilter("ignore", UserWarning)  # is still the same sequence
            points = self.sampler.random(n) * 2.0 - 1.0
        return [Proposal(p.astype(np.float32), self.lanes.get(i), i) for i, p in enumerate(points)]

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        for p, f in zip(proposals, feedback, strict=True):
            self.lanes.set(p.lane, observation(p.action, f.e_obs))
            if self._best is None or f.reward > self._best[0]:
                self._best = (f.reward, p.action)

    def recommend(self) -> np.ndarray:
        return self._best[1] if self._best else np.zeros(self.dim, np.float32)
