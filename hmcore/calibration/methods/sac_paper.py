"""The reference paper's SAC, run as published: Stable-Baselines3's own ``SAC.learn()`` over
:class:`hmcore.calibration.methods.env.HistoryMatchingEnv`.

One simulator call per one-step episode; observation ``[a_prev, E_prev]``; reward ``-E - P``
(a failed run: ``-failure_penalty - P``, never best), the paper's, whatever the case's
``objective``: the reproduction is defined by its reward (the campaign still chooses its best
call by the case's objective, as every campaign does); MLP policy, learning rate 3e-4, replay
buffer 10,000, batch 64, and SB3's SAC defaults for everything else (100 uniform-random steps
before learning, one gradient step per step, ``ent_coef="auto"``, ``net_arch=[256, 256]``,
``tau=0.005``; gamma is irrelevant to one-step episodes). The campaign keeps the best valid
candidate from the journal, as every campaign does.

With W workers the paper's serial loop becomes W copies of the env in one SB3 vectorised env:
each ``step`` sends the W actions to the simulator together (``evaluate_batch``, a Prefect task
each) and SB3 stores W transitions. To keep the paper's one gradient step per simulator call,
``gradient_steps=-1`` (as many as transitions collected) is used when W > 1; the differences
from the serial loop are that the W actions of a step come from the same policy and the first
learning step happens after ``ceil(100 / W)`` steps. The budget must be a multiple of W (the
vectorised env steps every copy at once).

The driver never runs the simulator: it is handed the campaign's calls (the injected
``evaluate_batch(jobs) -> records`` behind them), and records already journaled (a resumed
campaign) are replayed instead of simulated; every env step is a call, also one that repeats
a point (``learn()`` counts steps, as published); SB3 is
deterministic for a seed on CPU, so a replayed call must ask for the journaled action, and a
resume that does not is refused rather than mixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from hmcore.calibration.calls import BudgetedCalls
from hmcore.calibration.methods.env import HistoryMatchingEnv
from hmcore.scoring.evaluation import Evaluation


@dataclass(frozen=True)
class PaperSACSettings:
    """The paper's stated settings; every other SAC setting is Stable-Baselines3's default."""

    learning_rate: float = 3e-4
    buffer_size: int = 10_000
    batch_size: int = 64


class PaperSAC:
    """``sac-paper``: drives SB3's ``learn()`` loop itself (see :meth:`drive`)."""

    name = "sac-paper"
    reuses_points = False  # SB3's learn() counts its env steps: each one is a call, as published

    def __init__(self, dim: int, seed: int, settings: PaperSACSettings | None = None):
        self.dim = dim
        self.seed = seed
        self.settings = settings or PaperSACSettings()
        self.model = None

    def drive(self, calls: BudgetedCalls, workers: int) -> list[dict]:
        """Train SAC for the budget of simulator calls, ``workers`` per vectorised step;
        return every record in call order."""
        import torch
        from stable_baselines3 import SAC
        from stable_baselines3.common.logger import Logger

        budget = calls.budget
        if budget < 1 or workers < 1 or budget % workers:
            raise ValueError(f"sac-paper steps its {workers} env copies together, so the budget "
                             f"must be a positive multiple of workers; got budget={budget}, "
                             f"workers={workers} (try budget={max(workers, budget // workers * workers)})")
        torch.manual_seed(self.seed)
        torch.set_num_threads(1)  # leave the cores to the simulator subprocesses
        venv = BatchedEnv(calls, workers)
        s = self.settings
        self.model = SAC("MlpPolicy", venv, learning_rate=s.learning_rate,
                         buffer_size=s.buffer_size, batch_size=s.batch_size,
                         gradient_steps=-1 if workers > 1 else 1, seed=self.seed, device="cpu",
                         verbose=0)
        self.model.set_logger(Logger(folder=None, output_formats=[]))  # no SB3-* dir in /tmp
        self.model.learn(total_timesteps=budget)
        return venv.calls.records


class _Pending:
    """The evaluator of one env copy: hands the env the record of its current call."""

    def __init__(self):
        self.record: dict | None = None

    def __call__(self, values: dict[str, float]) -> Evaluation:
        return Evaluation.from_record(self.record)


class BatchedEnv(VecEnv):
    """W copies of :class:`HistoryMatchingEnv` whose simulator calls of a step run together.

    Call indices are consecutive: step s of copy i is call ``s * W + i``."""

    def __init__(self, calls: BudgetedCalls, workers: int):
        self.calls = calls
        self.pending = [_Pending() for _ in range(workers)]
        self.envs = [HistoryMatchingEnv(calls.space, p) for p in self.pending]
        self._actions: np.ndarray | None = None
        super().__init__(workers, self.envs[0].observation_space, self.envs[0].action_space)

    def reset(self):
        return np.stack([env.reset(seed=None)[0] for env in self.envs])

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.clip(np.asarray(actions, np.float32), -1.0, 1.0)

    def step_wait(self):
        batch = self.calls.run(self._actions)
        obs, rewards, dones, infos = [], [], [], []
        for env, pending, action, rec in zip(self.envs, self.pending, self._actions, batch):
            pending.record = rec
            o, r, terminated, truncated, info = env.step(action)  # r = -E - P, the paper's
            info = {**info, "call": rec["index"], "terminal_observation": o,
                    "TimeLimit.truncated": bool(truncated and not terminated)}
            o, _ = env.reset()  # one-step episodes: the next one starts from [a_prev, E_prev]
            obs.append(o)
            rewards.append(r)
            dones.append(True)
            infos.append(info)
        return np.stack(obs), np.array(rewards, np.float32), np.array(dones), infos

    # VecEnv's remaining abstract interface: nothing to close, render or forward
    def close(self) -> None:
        pass

    def get_attr(self, attr_name, indices=None):
        return [getattr(self.envs[i], attr_name) for i in self._indices(indices)]

    def set_attr(self, attr_name, value, indices=None) -> None:
        for i in self._indices(indices):
            setattr(self.envs[i], attr_name, value)

    def env_method(self, method_name, *method_args, indices=None, **method_kwargs):
        return [getattr(self.envs[i], method_name)(*method_args, **method_kwargs)
                for i in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False for _ in self._indices(indices)]

    def _indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)
