"""CMA-ES (the ``cma`` package) as an ask/tell proposer over the box [-1, 1]^d.

A generation of ``popsize`` candidates is asked from ``cma`` at once and handed out W at a
time; the generation is told back when all of it is evaluated, so a round may hand out fewer
than W (the rest of a generation). The popsize is cma's default raised to a multiple of W.
The cost of a candidate is ``-reward`` (E + P; a failed run's fixed penalty): CMA-ES uses
only the ranking, so the size of the failure penalty does not distort it.
"""

from __future__ import annotations

import math

import numpy as np

from hmcore.calibration.methods.base import Feedback, LaneMemory, Proposal

SIGMA0 = 0.5  # initial step, in action units (the box is 2 wide)


class CMAProposer:
    name = "cmaes"
    exploit_last = True  # the distribution's mean, often better than any sample

    def __init__(self, dim: int, seed: int, workers: int = 1):
        import cma

        self.dim = dim
        default = 4 + int(3 * math.log(dim))
        popsize = int(math.ceil(default / workers) * workers)
        self.es = cma.CMAEvolutionStrategy(np.zeros(dim), SIGMA0, {
            "bounds": [-1.0, 1.0], "seed": seed + 1, "popsize": popsize, "verbose": -9,
            "CMA_stds": None})
        self.lanes = LaneMemory(dim)
        self._queue: list[np.ndarray] = []
        self._generation: list[np.ndarray] = []
        self._told: dict[int, float] = {}
        self._handed = 0

    def ask(self, n: int) -> list[Proposal]:
        if self._handed == len(self._generation):
            self._generation = [np.asarray(x, float) for x in self.es.ask()]
            self._handed = 0
        k = min(n, len(self._generation) - self._handed)
        out = []
        for i in range(k):
            a = np.clip(self._generation[self._handed + i], -1.0, 1.0).astype(np.float32)
            out.append(Proposal(a, self.lanes.get(i), i, self._handed + i))
        self._handed += k
        return out

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        for p, f in self.lanes.tell(proposals, feedback):
            if 0 <= p.key < len(self._generation):  # key -1: the final recommendation
                self._told[p.key] = -f.reward
        if self._generation and len(self._told) == len(self._generation):
            self.es.tell(self._generation, [self._told[i] for i in range(len(self._generation))])
            self._told = {}

    def recommend(self) -> np.ndarray:
        return np.clip(np.asarray(self.es.mean, float), -1.0, 1.0).astype(np.float32)
