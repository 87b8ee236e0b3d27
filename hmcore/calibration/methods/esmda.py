"""Ensemble smoother with multiple data assimilation (``iterative_ensemble_smoother.ESMDA``).

The data are the residuals of the campaign's objective (version 2: the noise-whitened ones
under the likelihood, E's own under E, :meth:`hmcore.calibration.objective.Objective.residuals`;
version 1: always the whitened ones), so the observations are 0 with unit covariance. An ensemble of N members drawn uniformly in [-1, 1]^d is updated
``n_a`` times with the inflation factors ``alpha = n_a`` (equal), then the posterior is
evaluated: ``N * (n_a + 1)`` calls, every member a call; the calls left by the rounding go to
the posterior mean and then to members of the posterior redrawn from its mean and covariance.
``n_a = min(4, budget // 10)`` (at least 1) and ``N = budget // (n_a + 1)``, at least 2.
Members are clipped to the box before they run. A failed member has no residuals: the update
uses the others, and the failed one is replaced by a copy of a random updated member (a copy
that stays a copy is not simulated twice: its record is reused, and the call goes to the
redrawn posterior members at the end).
"""

from __future__ import annotations

import numpy as np

from hmcore.calibration.calls import BudgetedCalls, BudgetExhausted

MAX_ASSIMILATIONS = 4


def plan(budget: int) -> tuple[int, int]:
    """(ensemble size N, assimilations n_a) for a budget; ValueError when too small."""
    n_a = max(1, min(MAX_ASSIMILATIONS, budget // 10))
    n = budget // (n_a + 1)
    if n < 2:
        raise ValueError(f"esmda needs an ensemble of at least 2 members evaluated twice: a "
                         f"budget of at least 4 calls, got {budget}")
    return n, n_a


class ESMDADriver:
    name = "esmda"
    needs_residuals = True

    def __init__(self, dim: int, seed: int):
        self.dim = dim
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def drive(self, calls: BudgetedCalls, workers: int) -> list[dict]:
        import iterative_ensemble_smoother as ies

        n, n_a = plan(calls.budget)
        X = self.rng.uniform(-1.0, 1.0, (self.dim, n))
        smoother = None
        try:
            for _ in range(n_a):
                X = np.clip(X, -1.0, 1.0)
                res = [calls.objective.residuals(r) for r in calls.run(X.T, phase="ensemble")]
                ok = [k for k, r in enumerate(res) if r is not None]
                if len(ok) < 2:  # nothing to learn from: draw the ensemble again
                    X = self.rng.uniform(-1.0, 1.0, (self.dim, n))
                    continue
                Y = np.stack([res[k] for k in ok], axis=1)
                if smoother is None:
                    smoother = ies.ESMDA(np.ones(Y.shape[0]), np.zeros(Y.shape[0]),
                                         alpha=n_a, seed=self.seed)
                smoother.prepare_assimilation(Y=Y)
                X_ok = smoother.assimilate_batch(X=X[:, ok])
                X_new = X.copy()
                X_new[:, ok] = X_ok
                for k in set(range(n)) - set(ok):
                    X_new[:, k] = X_ok[:, self.rng.integers(len(ok))]
                X = X_new
            X = np.clip(X, -1.0, 1.0)
            calls.run(X.T, phase="posterior")
            extra = [np.clip(X.mean(axis=1), -1.0, 1.0)]
            cov = np.cov(X) + 1e-9 * np.eye(self.dim)
            while calls.left > 0:  # more than once only when a point was simulated already
                while len(extra) < calls.left:
                    extra.append(np.clip(self.rng.multivariate_normal(X.mean(axis=1), cov),
                                         -1, 1))
                calls.run(np.array(extra[: calls.left]), phase="posterior_extra")
                extra = []
        except BudgetExhausted:
            pass
        return calls.records
