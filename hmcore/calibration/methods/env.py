"""The Gymnasium environment of the reference method: one simulator call per one-step episode.

* action: Box ``[-1, 1]^n``, mapped linearly to the parameter bounds by
  :meth:`hmcore.model.parameters.ParameterSpace.to_values` (the only place that does it);
* observation: ``[a_prev (n), E_prev (1)]`` - the previous episode's action and misfit (a failed
  run's E is the failure penalty), E clipped to ``[0, e_cap]``;
* reward: ``-E - P_phys`` (``-failure_penalty - P_phys`` for a failed run);
* ``info``: parameter values, status, reason, misfit breakdown and coverage - what the
  proposal determines, so the same action gives the same step (gymnasium's ``check_env``
  checks that); where the run was written is the journal's business, not the step's.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import gymnasium as gym
import numpy as np

from hmcore.model.parameters import ParameterSpace

E_CAP = 10.0


def observation_space(dim: int, e_cap: float = E_CAP) -> gym.spaces.Box:
    low = np.concatenate([-np.ones(dim), [0.0]]).astype(np.float32)
    high = np.concatenate([np.ones(dim), [e_cap]]).astype(np.float32)
    return gym.spaces.Box(low, high, dtype=np.float32)


def action_space(dim: int) -> gym.spaces.Box:
    return gym.spaces.Box(-1.0, 1.0, shape=(dim,), dtype=np.float32)


def observation(action: np.ndarray, e_obs: float, e_cap: float = E_CAP) -> np.ndarray:
    """``[a, clip(E)]`` as float32."""
    e = e_cap if not math.isfinite(e_obs) else min(max(e_obs, 0.0), e_cap)
    return np.concatenate([np.clip(np.asarray(action, np.float32), -1, 1), [e]]).astype(np.float32)


def observed_misfit(evaluation) -> float:
    """E for the observation: the misfit of a scored run, the penalty of a failed one."""
    return evaluation.E if math.isfinite(evaluation.E) else evaluation.penalty


class HistoryMatchingEnv(gym.Env):
    """One-step episodes; ``evaluate(values) -> Evaluation`` runs the simulator (injected)."""

    metadata = {"render_modes": []}

    def __init__(self, space: ParameterSpace, evaluate: Callable[[dict[str, float]], Any] | None,
                 e_cap: float = E_CAP):
        super().__init__()
        self.space = space
        self._evaluate = evaluate
        self.e_cap = e_cap
        self.action_space = action_space(space.dim)
        self.observation_space = observation_space(space.dim, e_cap)
        self._obs = observation(np.zeros(space.dim), 0.0, e_cap)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return self._obs.copy(), {}

    def step(self, action):
        if self._evaluate is None:
            raise RuntimeError("this environment was built without an evaluator (spaces only)")
        action = np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0)
        values = self.space.to_values(action)
        ev = self._evaluate(values)
        self._obs = observation(action, observed_misfit(ev), self.e_cap)
        info = {"params": values, "status": ev.status.value, "reason": ev.reason, "E": ev.E,
                "penalty": ev.penalty, "per_response": ev.per_response,
                "coverage": ev.coverage}
        return self._obs.copy(), float(ev.reward), True, False, info
