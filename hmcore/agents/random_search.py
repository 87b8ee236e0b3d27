"""Uniform random search: the simplest proposer, a baseline and a fast test double."""

from __future__ import annotations

import numpy as np

from hmcore.agents.base import Feedback, LaneMemory, Proposal
from hmcore.env import observation


class RandomProposer:
    name = "random"
    exploit_last = False  # its recommendation is a point already evaluated

    def __init__(self, dim: int, seed: int):
        self.dim = dim
        self.rng = np.random.default_rng(seed)
        self.lanes = LaneMemory(dim)
        self._best: tuple[float, np.ndarray] | None = None

    def ask(self, n: int) -> list[Proposal]:
        return [Proposal(self.rng.uniform(-1, 1, self.dim).astype(np.float32), self.lanes.get(i), i)
                for i in range(n)]

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        for p, f in zip(proposals, feedback, strict=True):
            self.lanes.set(p.lane, observation(p.action, f.e_obs))
            if self._best is None or f.reward > self._best[0]:
                self._best = (f.reward, p.action)

    def recommend(self) -> np.ndarray:
        return self._best[1] if self._best else np.zeros(self.dim, np.float32)
