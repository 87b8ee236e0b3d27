"""Parameter sets drawn from the Laplace posterior at a campaign's best call: the members of
its forecast (simulated after the fit, apart from the budget).

The posterior of the scaled parameters ``u`` in ``[-1, 1]^d`` given the history is taken as
the Gaussian likelihood of the linearised residuals (:mod:`hmcore.scoring.identifiability`:
mean the best call's ``u*``, covariance ``C = (J^T J)^+`` over the directions the data
determine) times the box as a uniform prior. So a draw is ``u* + C^(1/2) xi`` (``xi``
standard normal), plus, along the directions the data do not determine (the null space of
``J``), a uniform step spanning the box; a draw outside the box is rejected and drawn again:
the truncation to the box is the prior's, not a clip. This is the randomised form of the
Gauss-Newton posterior (Oliver, Reynolds & Liu 2008, *Inverse Theory for Petroleum Reservoir
Characterization and History Matching*, Cambridge, ch. 10, sampling the Laplace
approximation; Tarantola 2005, ch. 3).

**Inflation when the best call does not fit within the noise.** When the residuals' mean
square ``s2 = chi2 / (n - d)`` is above 1 the model misses the data by more than the noise
the campaign assumes; ``C`` is then multiplied by ``s2`` (the Birge ratio, the regression
convention for an unknown noise level), so that the band widens with the misfit rather than
claiming a certainty the fit does not have. ``s2 <= 1`` leaves ``C`` as it is.

Numpy in, numpy out; the draws depend on the generator passed in only.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hmcore.scoring.identifiability import Identifiability

DEFAULT_DRAWS = 20
"""Parameter sets a campaign's forecast draws from its posterior (``--forecast-draws``)."""
MIN_BUDGET = 50
"""A campaign of fewer calls draws none by default: its best call is seldom a converged fit,
and the Laplace approximation stands on one."""
BATCH = 64
"""Points drawn at a time (fixed, so that a larger ``count`` extends the same draws)."""
MAX_TRIES = 1000
"""Draws tried per draw kept before the rest are given up (a posterior almost all outside
the box)."""


@dataclass(frozen=True, eq=False)
class Draws:
    """``points`` (m, d) scaled points in the box, from the posterior centred on ``centre``
    (d,); ``inflation``: the factor ``C`` was multiplied by (``max(1, s2)``); ``tried``: the
    draws made to keep these (the rest fell outside the box or broke ``accept``); ``free``:
    the parameters the data do not determine (drawn across the box)."""

    points: np.ndarray
    centre: np.ndarray
    inflation: float
    tried: int
    free: tuple[int, ...]


def laplace_draws(found: Identifiability, count: int, rng: np.random.Generator,
                  accept: Callable[[np.ndarray], np.ndarray] | None = None) -> Draws:
    """``count`` scaled points from the box-truncated Laplace posterior of ``found`` (see the
    module docstring); fewer when the box holds almost none of it (``MAX_TRIES`` per draw).
    ``accept``: (m, d) points -> (m,) bool, a further prior constraint a point must meet (the
    physics checks its values break before any simulation); a rejected point is drawn
    again, as one outside the box."""
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    post = found.laplace
    u = np.asarray(found.best_scaled, float)
    d = u.size
    s2 = post.s2 if math.isfinite(post.s2) else 1.0
    inflation = max(1.0, float(s2))
    cov = np.asarray(post.covariance, float) * inflation
    w, v = np.linalg.eigh((cov + cov.T) / 2.0)
    root = v * np.sqrt(np.clip(w, 0.0, None))  # C^(1/2) up to a rotation: root @ root.T = C
    null = _null_basis(post.covariance, post.undetermined)
    kept: list[np.ndarray] = []
    tried = 0
    while len(kept) < count and tried < MAX_TRIES * max(count, 1):
        batch = BATCH  # fixed: the first k draws kept are the same whatever ``count`` is
        z = rng.standard_normal((batch, d)) @ root.T
        if null.shape[1]:
            z += rng.uniform(-2.0 * math.sqrt(d), 2.0 * math.sqrt(d),
                             (batch, null.shape[1])) @ null.T
        points = u + z
        tried += batch
        inside = np.all(np.abs(points) <= 1.0, axis=1)
        if accept is not None and inside.any():
            inside[inside] = np.asarray(accept(points[inside]), bool)
        kept.extend(points[inside][: count - len(kept)])
    points = np.array(kept, float).reshape(-1, d)
    return Draws(points, u, inflation, tried,
                 tuple(int(i) for i in np.flatnonzero(post.undetermined)))


def _null_basis(covariance: np.ndarray, undetermined: np.ndarray) -> np.ndarray:
    """(d, k) orthonormal directions the data do not determine: the eigenvectors of the
    determined covariance with a zero eigenvalue, when some parameter is undetermined."""
    d = covariance.shape[0]
    if not np.any(undetermined):
        return np.zeros((d, 0))
    w, v = np.linalg.eigh((covariance + covariance.T) / 2.0)
    return v[:, w <= 1e-12 * max(float(w.max()), 1e-300)]
