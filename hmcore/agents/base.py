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
    handed the evaluator and returns every record in call order; it never runs the simulator
    itself and replays ``done`` (journaled) calls instead of evaluating them."""

    name: str

    def drive(self, space, evaluate_batch, budget: int, workers: int,
              done: dict[int, dict] | None = None) -> list[dict]: ...


class LaneMemory:
    """The last observation of each parallel lane (``[a_prev, E_prev]``, zeros at start)."""

    def __init__(self, dim: int):
        self.dim = dim
        self._obs: dict[int, np.ndarray] = {}

    def get(self, lane: int) -> np.ndarray:
        from hmcore.env import observation

        return self._obs.get(lane, observation(np.zeros(self.dim), 0.0)).copy()

    def set(self, lane: int, obs: np.ndarray) -> None:
        self._obs[lane] = obs
