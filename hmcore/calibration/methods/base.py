"""The ask/tell interface every proposer implements (SAC now; CMA-ES, BO, DE, ES-MDA later).

``ask(n)`` returns n proposals (actions in ``[-1, 1]^dim``) meant to be evaluated together;
``tell(proposals, feedback)`` gives their results back in the same order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Proposal:
    action: np.ndarray          # shape (dim,), in [-1, 1]
    observation: np.ndarray     # what the agent saw when proposing: [a_prev, E_prev]
    lane: int = 0               # parallel stream the proposal belongs to
    key: int = -1               # the proposer's own handle (a trial or population slot)


@dataclass(frozen=True)
class Feedback:
    reward: float               # -E - P (or -failure_penalty - P)
    e_obs: float                # E of a scored run, the penalty of a failed one
    scored: bool = True         # False for a failed run (no E: its reward is the fixed penalty)
    penalty: float = 0.0        # P: the physics penalty in the reward (ablations learn without)
    worst: float | None = None  # the worst well-response loss (robust-reward ablation)


class Proposer(Protocol):
    name: str

    def ask(self, n: int) -> list[Proposal]: ...

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None: ...

    def recommend(self) -> np.ndarray:
        """The proposer's current best guess of the action (not necessarily evaluated)."""
        ...


@runtime_checkable
class Driver(Protocol):
    """A method that runs its own loop (SB3's ``learn()``, say) instead of ask/tell: it is
    handed the campaign's :class:`~hmcore.calibration.calls.BudgetedCalls` (the space, the
    budget, the journal to replay, the points simulated, the pre-simulation checks) and
    returns every record in call order; it never runs the simulator itself. A driver that
    counts its own steps as calls says so with ``reuses_points = False``."""

    name: str

    def drive(self, calls, workers: int) -> list[dict]: ...


class Sampler:
    """A proposer that learns nothing (random search, Sobol'): subclasses draw ``_points(n)``
    in [-1, 1]; it keeps each lane's observation and the best action told."""

    exploit_last = False  # its recommendation is a point already evaluated

    def __init__(self, dim: int):
        self.dim = dim
        self.lanes = LaneMemory(dim)
        self._best: tuple[float, np.ndarray] | None = None

    def _points(self, n: int) -> np.ndarray:
        raise NotImplementedError

    def ask(self, n: int) -> list[Proposal]:
        return [Proposal(np.asarray(a, np.float32), self.lanes.get(i), i)
                for i, a in enumerate(self._points(n))]

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        for p, f in self.lanes.tell(proposals, feedback):
            if self._best is None or f.reward > self._best[0]:
                self._best = (f.reward, p.action)

    def recommend(self) -> np.ndarray:
        return self._best[1] if self._best else np.zeros(self.dim, np.float32)


class LaneMemory:
    """The last observation of each parallel lane (``[a_prev, E_prev]``, zeros at start)."""

    def __init__(self, dim: int):
        self.dim = dim
        self._obs: dict[int, np.ndarray] = {}

    def get(self, lane: int) -> np.ndarray:
        from hmcore.calibration.methods.env import observation

        return self._obs.get(lane, observation(np.zeros(self.dim), 0.0)).copy()

    def set(self, lane: int, obs: np.ndarray) -> None:
        self._obs[lane] = obs

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]
             ) -> list[tuple[Proposal, Feedback]]:
        """What a proposer's ``tell`` does first: each told proposal's lane remembers what it
        led to (``[a, E]``). Returns the (proposal, feedback) pairs in order, for the proposer
        to hand to its library."""
        from hmcore.calibration.methods.env import observation  # env loads gymnasium

        pairs = list(zip(proposals, feedback, strict=True))
        for p, f in pairs:
            self.set(p.lane, observation(p.action, f.e_obs))
        return pairs
