"""Bayesian optimisation: optuna's Gaussian-process sampler (``GPSampler``) by ask/tell.

Each proposal is an optuna trial over ``a_i`` in [-1, 1]; W trials are asked before their
results are told. The GP models ``log10`` of the cost every method is given, ``-reward``:
E + P for a scored run (valid or penalised), the campaign's failure penalty for a failed run
(the reward the paper defines, not a score made up for optuna; the trial carries the
failure in its user attributes). E spans decades, and on the log scale a failure is a high
cost, not an outlier that flattens the model. Told as FAIL trials instead, failures are
invisible to the GP: measured on a 5-d problem with a failing corner, it then proposed 17 of
its last 20 calls there.
"""

from __future__ import annotations

import numpy as np

from hmcore.calibration.methods.base import Feedback, LaneMemory, Proposal

COST_FLOOR = 1e-12  # log10 of a cost of 0

STARTUP_TRIALS = 10  # quasi-random trials before the GP (optuna's default is 10)


class BOProposer:
    name = "bo"
    exploit_last = False  # its recommendation is a point already evaluated

    def __init__(self, dim: int, seed: int):
        import optuna
        import torch

        torch.set_num_threads(1)  # as the SAC learners: the cores are the simulators', and a
        #                           resumed campaign replays the GP's proposals exactly

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        sampler = optuna.samplers.GPSampler(seed=seed, n_startup_trials=STARTUP_TRIALS)
        self.study = optuna.create_study(direction="minimize", sampler=sampler)
        self.dim = dim
        self.lanes = LaneMemory(dim)
        self._trials: dict[int, object] = {}

    def ask(self, n: int) -> list[Proposal]:
        out = []
        for i in range(n):
            trial = self.study.ask()
            a = np.array([trial.suggest_float(f"a{k}", -1.0, 1.0) for k in range(self.dim)],
                         np.float32)
            self._trials[trial.number] = trial
            out.append(Proposal(a, self.lanes.get(i), i, trial.number))
        return out

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        for p, f in self.lanes.tell(proposals, feedback):
            trial = self._trials.pop(p.key, None)
            if trial is None:
                continue
            if not f.scored:
                trial.set_user_attr("failed", "simulation failed: cost is the failure penalty")
            self.study.tell(trial, float(np.log10(max(-f.reward, COST_FLOOR))))

    def recommend(self) -> np.ndarray:
        try:
            best = self.study.best_trial
        except ValueError:  # nothing scored yet
            return np.zeros(self.dim, np.float32)
        return np.array([best.params[f"a{k}"] for k in range(self.dim)], np.float32)
