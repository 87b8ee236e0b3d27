"""Soft Actor-Critic (Stable-Baselines3) driven as an ask/tell proposer.

The reference method trains SB3's SAC on :class:`hmcore.calibration.methods.env.HistoryMatchingEnv`, one simulator
call per one-step episode. Here the same SB3 model is driven step by step so that the caller
decides how simulations run (W at once on a Prefect task runner): ``ask`` samples the
stochastic policy (uniform random during ``learning_starts``), ``tell`` puts the transitions in
SB3's replay buffer and runs ``gradient_steps`` SAC updates per call.

What the critic learns from is the reward -E - P bounded below: a failed run's fixed penalty
(10 by default) is two orders of magnitude beyond the spread of E between proposals (~0.01-1),
and left as it is, a squared-error critic spends itself on that cliff and the policy ends in
corners the critic extrapolates wrongly (measured on a 5-d quadratic: late-call mean E 0.10-0.23,
worse than random, against 0.01-0.05 with the bound). So each learning cost ``E + P`` is
capped at ``failure_cost_factor`` x the worst scored cost seen so far; the caps are refreshed in
the replay buffer before every training round. The journaled reward stays -E - P.

Options, off by default (``agent_settings``; measured in docs/benchmarks.md): a short
scrambled-Sobol' start (``start="sobol"``, e.g. ``learning_starts=10``); the critic on
``-log(cost)`` (``reward_transform="log"``: near the optimum 1.1x the floor and the floor
differ by 0.1 in log but by 1e-4 in E); and critic-chosen proposals (``candidates=512``):
each proposal the best of that many actions by the critic (the smaller of its twin Q
values), drawn from the policy and around the incumbent, inside a trust region around the
best call (:mod:`hmcore.calibration.methods.trust_region`), W proposals kept apart. Why they
stay off (they were tried together as a second version of the default): docs/benchmarks.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import gymnasium as gym
import numpy as np

from hmcore.calibration.registry import VERSIONS
from hmcore.calibration.methods.base import Feedback, LaneMemory, Proposal
from hmcore.calibration.methods.trust_region import TrustRegion
from hmcore.calibration.methods.env import action_space, observation, observation_space


VERSION = VERSIONS["sac"]  # what the campaign store binds a sac campaign to


@dataclass(frozen=True)
class SACSettings:
    learning_rate: float = 3e-4
    buffer_size: int = 10_000
    batch_size: int = 64
    learning_starts: int = 40
    start: Literal["sobol", "uniform"] = "uniform"  # how the first learning_starts calls are drawn
    gradient_steps: int = 8        # SAC updates per simulator call
    reward_scale: float = 10.0     # learning rewards are multiplied by this
    reward_transform: Literal["log", "linear"] = "linear"  # learn -cost or -log(cost)
    net_arch: tuple[int, ...] = (64, 64)
    ent_coef: str | float = "auto_0.01"  # SB3 auto-tuning from 0.01: 1.0 drowns rewards ~1e-2
    failure_cost_factor: float = 1.5  # learning cost cap: this x the worst scored cost so far
    candidates: int = 0            # actions scored by the critic per proposal (0: a policy sample)
    trust_region: bool = True      # candidates inside a trust region around the incumbent
    spread: float = 0.25           # proposals of one batch at least this x the region's side apart
    # ablations: what the agent learns from; the campaign is judged the same way
    penalty_in_reward: bool = True  # False: a scored run's learning cost is E, without P
    robust_lambda: float = 0.0     # > 0: learning cost + this x the worst well-response loss


class SACProposer:
    name = "sac"
    exploit_last = True  # the deterministic policy ends the campaign

    def __init__(self, dim: int, seed: int, settings: SACSettings | None = None):
        import torch
        from stable_baselines3 import SAC
        from stable_baselines3.common.logger import Logger

        self.settings = settings or SACSettings()
        self.dim = dim
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        torch.manual_seed(seed)
        torch.set_num_threads(1)  # leave the cores to the simulator subprocesses
        env = _SpacesOnlyEnv(dim)
        s = self.settings
        self.model = SAC("MlpPolicy", env, learning_rate=s.learning_rate, buffer_size=s.buffer_size,
                         batch_size=s.batch_size, learning_starts=s.learning_starts, gamma=0.0,
                         ent_coef=s.ent_coef, policy_kwargs={"net_arch": list(s.net_arch)},
                         seed=seed, device="cpu", verbose=0)
        self.model.set_logger(Logger(folder=None, output_formats=[]))  # no SB3-* dir in /tmp
        self.lanes = LaneMemory(dim)
        self.n_told = 0
        self._costs: list[tuple[float, bool]] = []  # (E + P, scored) of each transition told
        self._best: tuple[float, np.ndarray] | None = None
        self.region = TrustRegion(dim)
        self._start = None
        if s.start == "sobol":
            from scipy.stats import qmc

            self._start = qmc.Sobol(dim, scramble=True, seed=np.random.default_rng([seed, 1]))

    def ask(self, n: int) -> list[Proposal]:
        obs = np.stack([self.lanes.get(i) for i in range(n)])
        if self.n_told < self.settings.learning_starts:
            actions = self._start_points(n)
        elif self.settings.candidates > 0:
            actions = self._critic_choice(obs, n)
        else:
            actions, _ = self.model.predict(obs, deterministic=False)
        return [Proposal(np.asarray(a, np.float32), o, i) for i, (a, o) in enumerate(zip(actions, obs))]

    def _start_points(self, n: int) -> np.ndarray:
        if self._start is None:
            return self.rng.uniform(-1, 1, (n, self.dim)).astype(np.float32)
        import warnings

        with warnings.catch_warnings():  # scipy warns when n is not a power of 2
            warnings.simplefilter("ignore", UserWarning)
            return (self._start.random(n) * 2.0 - 1.0).astype(np.float32)

    def _candidates(self, obs: np.ndarray) -> np.ndarray:
        """Policy samples and Gaussian steps around the incumbent, inside the trust region."""
        m = self.settings.candidates
        lo, hi = self.region.bounds() if self.settings.trust_region else (-np.ones(self.dim),
                                                                          np.ones(self.dim))
        policy, _ = self.model.predict(np.repeat(obs[:1], m // 2, axis=0), deterministic=False)
        centre = self._best[1] if self._best is not None else np.zeros(self.dim)
        local = centre + self.rng.normal(0.0, 1.0, (m - m // 2, self.dim)) * (hi - lo) / 4.0
        return np.clip(np.concatenate([policy, local]), lo, hi).astype(np.float32)

    def _q(self, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """The smaller of the twin critics' values of ``actions`` seen from ``obs``."""
        import torch

        with torch.no_grad():
            o = torch.as_tensor(np.repeat(obs[:1], len(actions), axis=0))
            q = torch.min(*self.model.critic(o, torch.as_tensor(actions)))
        return q.numpy().ravel()

    def _critic_choice(self, obs: np.ndarray, n: int) -> np.ndarray:
        """The n best candidates by the critic, each at least ``spread`` x the region's side
        from those already chosen (fewer apart: the next best)."""
        cand = self._candidates(obs)
        order = np.argsort(-self._q(obs, cand))
        gap = self.settings.spread * (self.region.side if self.settings.trust_region else 2.0)
        chosen: list[int] = []
        for k in order:
            if all(np.max(np.abs(cand[k] - cand[j])) >= gap for j in chosen):
                chosen.append(k)
            if len(chosen) == n:
                break
        chosen += [k for k in order if k not in chosen][: n - len(chosen)]
        return cand[chosen]

    def cost_of(self, f: Feedback) -> float:
        """The cost the agent learns from: ``-reward`` (E + P, or a failed run's fixed penalty
        + P), less P or plus ``robust_lambda`` x the worst well-response loss in an ablation."""
        cost = -f.reward
        if f.scored and not self.settings.penalty_in_reward:
            cost -= f.penalty
        if f.scored and self.settings.robust_lambda > 0 and f.worst is not None:
            cost += self.settings.robust_lambda * f.worst
        return float(cost)

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        costs = [self.cost_of(f) for f in feedback]
        for p, f, cost in zip(proposals, feedback, costs, strict=True):
            next_obs = observation(p.action, f.e_obs)
            self.model.replay_buffer.add(p.observation[None], next_obs[None], p.action[None],
                                         np.array([-cost * self.settings.reward_scale]),
                                         np.array([True]), [{}])
            self.lanes.set(p.lane, next_obs)
            self._costs.append((cost, f.scored))
            self.n_told += 1
            if self._best is None or -cost > self._best[0]:
                self._best = (-cost, p.action)
        self.region.update(np.stack([p.action for p in proposals]),
                           np.array([c if f.scored else np.inf for c, f in zip(costs, feedback)]))
        self.model.num_timesteps = self.n_told
        if self.n_told >= self.settings.learning_starts:
            self._bound_rewards()
            self.model.train(gradient_steps=self.settings.gradient_steps * len(proposals),
                             batch_size=self.settings.batch_size)

    def learning_costs(self) -> np.ndarray:
        """The costs the critic learns from, in told order: ``E + P`` capped at
        ``failure_cost_factor`` x the worst scored cost (uncapped while none is scored)."""
        costs = np.array([c for c, _ in self._costs], float)
        scored = np.array([s for _, s in self._costs], bool)
        if scored.any():
            costs = np.minimum(costs, self.settings.failure_cost_factor * costs[scored].max())
        return costs

    def learning_rewards(self) -> np.ndarray:
        """What the critic learns, in told order: ``-cost`` or ``-log(cost)`` of the capped
        costs, times ``reward_scale``."""
        costs = self.learning_costs()
        if self.settings.reward_transform == "log":
            costs = np.log(np.maximum(costs, 1e-12))
        return -costs * self.settings.reward_scale

    def _bound_rewards(self) -> None:
        buf = self.model.replay_buffer
        rewards = self.learning_rewards()[-buf.buffer_size:]
        slots = (buf.pos - len(rewards) + np.arange(len(rewards))) % buf.buffer_size
        buf.rewards[slots, 0] = rewards

    def recommend(self) -> np.ndarray:
        """The deterministic policy's action from the best lane's observation; with critic
        choice, the critic's best of that action and fresh candidates (never the incumbent
        itself: it is already evaluated)."""
        obs = self.lanes.get(0)
        action, _ = self.model.predict(obs[None], deterministic=True)
        action = np.asarray(action[0], np.float32)
        if self.settings.candidates <= 0 or self.n_told < self.settings.learning_starts:
            return action
        if self.settings.trust_region:  # the critic is trusted inside the region only
            action = np.clip(action, *self.region.bounds()).astype(np.float32)
        pool = np.concatenate([action[None], self._candidates(obs[None])])
        return pool[int(np.argmax(self._q(obs[None], pool)))]


class _SpacesOnlyEnv(gym.Env):
    """A stand-in env that only carries the spaces SB3 needs to build the model."""

    def __init__(self, dim: int):
        self.observation_space = observation_space(dim)
        self.action_space = action_space(dim)

    def reset(self, *, seed=None, options=None):
        return self.observation_space.sample(), {}

    def step(self, action):  # pragma: no cover - never stepped: ask/tell drives the model
        raise RuntimeError("spaces-only environment")
