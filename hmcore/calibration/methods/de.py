"""Differential evolution (nevergrad's ``DE``) as an ask/tell proposer over [-1, 1]^d.

nevergrad asks and tells one candidate at a time and allows ``num_workers`` candidates in
flight, so W workers are filled as they are. The population is ``POPSIZE`` (2 x 5 parameters;
nevergrad's "standard" 30 would spend a 100-call budget on three generations). The loss is
``-reward`` (E + P; a failed run's fixed penalty), which DE uses only to compare.
"""

from __future__ import annotations

import numpy as np

from hmcore.calibration.methods.base import Feedback, LaneMemory, Proposal

POPSIZE = 10


class DEProposer:
    name = "de"
    exploit_last = False  # its recommendation is a point already evaluated

    def __init__(self, dim: int, seed: int, budget: int = 200, workers: int = 1):
        import nevergrad as ng

        param = ng.p.Array(shape=(dim,), lower=-1.0, upper=1.0)
        param.random_state = np.random.RandomState(seed)
        de = ng.families.DifferentialEvolution(popsize=POPSIZE)
        self.opt = de(parametrization=param, budget=budget, num_workers=workers)
        self.dim = dim
        self.lanes = LaneMemory(dim)
        self._pending: dict[int, object] = {}
        self._next = 0

    def ask(self, n: int) -> list[Proposal]:
        out = []
        for i in range(n):
            cand = self.opt.ask()
            key = self._next
            self._next += 1
            self._pending[key] = cand
            out.append(Proposal(np.clip(cand.value, -1, 1).astype(np.float32),
                                self.lanes.get(i), i, key))
        return out

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        for p, f in self.lanes.tell(proposals, feedback):
            cand = self._pending.pop(p.key, None)
            if cand is not None:
                self.opt.tell(cand, float(-f.reward))

    def recommend(self) -> np.ndarray:
        return np.clip(self.opt.provide_recommendation().value, -1, 1).astype(np.float32)
