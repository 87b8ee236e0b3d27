"""What the data pin down after a least-squares fit: each parameter's standard deviation and 95 %
interval, their correlations, the pairs the data cannot separate and the parameters they do not
inform, from the Laplace (Gauss-Newton) approximation of the posterior at the best point.

The model: ``r(u)`` (n,) the noise-whitened residuals of the fitted history (each entry
``(simulated - observed) / sigma``, AR(1)-prewhitened: unit variance and independent when the
model is right and the noise is what the campaign assumes), ``u`` (d,) the scaled parameters
in ``[-1, 1]^d`` (:class:`hmcore.model.parameters.Scaling`: linear in the value or in its log).
Near the best point ``u*`` the residuals are about linear, ``r(u) ~ r* + J (u - u*)`` with
``J`` (n, d) their Jacobian, so that the likelihood ``exp(-|r|^2 / 2)`` is a Gaussian in ``u``
with covariance

    C = (J^T J)^-1

(the Gauss-Newton, or Laplace, approximation of the posterior covariance with the data
covariance whitened to the identity and no prior term: Tarantola 2005, *Inverse Problem
Theory and Methods for Model Parameter Estimation*, SIAM, ch. 3, the posterior of a linearised
least-squares problem; Oliver, Reynolds & Liu 2008, *Inverse Theory for Petroleum Reservoir
Characterization and History Matching*, Cambridge, the Gauss-Newton posterior covariance
``(G^T C_D^-1 G + C_M^-1)^-1`` without ``C_M^-1``). The box is the only prior: it clips the
intervals, it does not narrow the covariance.

**Not scaled by the residual variance.** Regression software multiplies ``C`` by
``s^2 = |r*|^2 / (n - d)`` when the noise level is unknown (scipy's ``curve_fit`` with
``absolute_sigma=False``). hmflow's residuals are already in units of the noise its objective
states (given in the history, stated in ``[noise]``, or estimated from the data and refined
from the fit's own residuals: :mod:`hmcore.calibration.objective`), so scaling again would
count the noise level twice; :attr:`Laplace.s2` is returned so that a report can say how far
the residuals are from that noise and what the regression convention would change (each
standard deviation times ``sqrt(s2)``).

**Directions the data do not see.** Where ``J^T J`` is singular (a parameter that moves no
residual, or two that act only through one combination), ``C`` is computed from the singular
values above ``rcond`` times the largest; a parameter with a share of the null space has an
infinite standard deviation (its interval is the whole box), and the correlations are the
limit of ``(J^T J + eps I)^-1``'s as ``eps -> 0``: between two parameters of the null space
the correlation of its projector (``-1`` for two that act only through their sum), 0 between
such a parameter and a determined one.

Everything here is numpy in, numpy or frozen dataclasses out; nothing reads a store or runs a
simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hmcore.model.parameters import Scaling

Z95 = 1.959963984540054
"""The two-sided 95 % quantile of the standard normal."""
PAIR_CORRELATION = 0.9
"""Two parameters whose posterior correlation is beyond this (in absolute value) are a pair
the data cannot separate: they fix a combination of the two, not each."""
UNINFORMED_SHARE = 0.5
"""A parameter whose 95 % interval (clipped to the box) covers more than this share of its
range (in scaled units) is one the data do not inform."""
RCOND = 1e-10
"""Singular values of J below this times the largest are taken as zero (a null direction)."""
MAX_STENCIL_STEP = 0.1
"""The largest finite-difference step (scaled units, 5 % of a range) a stencil run may take."""
MAX_BASE_DISTANCE = 0.1
"""How far (Euclidean, scaled units) a stencil's base may be from the point it stands for."""


@dataclass(frozen=True, eq=False)
class Laplace:
    """The Gaussian approximation of the posterior of the scaled parameters (d of them) from
    ``n`` whitened residuals: ``covariance`` (d, d) over the determined directions (the
    pseudo-inverse of ``J^T J``), ``sd`` (d,) (inf where ``undetermined``), ``correlation``
    (d, d) (1 on the diagonal, see the module docstring for the null space), ``undetermined``
    (d,) bool, ``rank`` of J, ``chi2`` = ``|r|^2``, ``n`` and ``s2`` = ``chi2 / (n - d)``
    (NaN when n <= d)."""

    covariance: np.ndarray
    sd: np.ndarray
    correlation: np.ndarray
    undetermined: np.ndarray
    rank: int
    chi2: float
    n: int
    s2: float


def laplace(J: np.ndarray, r: np.ndarray, n: int | None = None, rcond: float = RCOND) -> Laplace:
    """The Laplace approximation at a least-squares point: ``J`` (n, d) the Jacobian of the
    whitened residuals ``r`` (n,) there, in scaled parameter units; ``n`` the number of
    independent residuals (default ``len(r)``; a whitened vector may hold rows that are not
    noise, :meth:`~hmcore.scoring.observations.ObservationSet.n_noise`)."""
    J = np.asarray(J, float)
    r = np.asarray(r, float)
    if J.ndim != 2 or r.shape != (J.shape[0],):
        raise ValueError(f"J must be (n, d) and r (n,), got {J.shape} and {r.shape}")
    d = J.shape[1]
    n = int(len(r) if n is None else n)
    _, s, vt = np.linalg.svd(J, full_matrices=True)  # vt (d, d): every direction
    keep = np.zeros(d, bool)
    if s.size and s[0] > 0:
        keep[: s.size] = s > rcond * s[0]
    v = vt.T
    vk = v[:, keep]
    cov = (vk / s[keep[: s.size]] ** 2) @ vk.T
    null = v[:, ~keep]
    proj = null @ null.T
    undetermined = np.diag(proj) > 1e-8
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sd[undetermined] = np.inf
    corr = np.zeros((d, d))
    det = ~undetermined
    if det.any():
        sdd = np.sqrt(np.diag(cov)[det])
        corr[np.ix_(det, det)] = cov[np.ix_(det, det)] / np.outer(sdd, sdd)
    if undetermined.any():
        p = np.sqrt(np.diag(proj)[undetermined])
        corr[np.ix_(undetermined, undetermined)] = (proj[np.ix_(undetermined, undetermined)]
                                                    / np.outer(p, p))
    np.fill_diagonal(corr, 1.0)
    corr = np.clip(corr, -1.0, 1.0)
    chi2 = float(r @ r)
    return Laplace(cov, sd, corr, undetermined, int(keep.sum()), chi2, n,
                   chi2 / (n - d) if n > d else float("nan"))


@dataclass(frozen=True, eq=False)
class Identifiability:
    """What the data pin down, per parameter (d of them, in ``names``' order).

    Scaled units (``[-1, 1]`` per range): ``best_scaled`` (d,), ``low_scaled`` /
    ``high_scaled`` (d,) the 95 % interval ``best +- 1.96 sd`` clipped to the box,
    ``clipped_low`` / ``clipped_high`` (d,) bool where the clip cut it, ``share`` (d,) the
    share of the range the clipped interval covers. Physical units: ``best``, ``low``,
    ``high`` (d,), ``sd`` (d,) the standard deviation by the delta method at the best value
    (``sd_scaled`` times the value's derivative in the scaled coordinate; inf where
    undetermined), ``factor`` (d,) for a log-scaled parameter the multiplicative standard
    deviation ``exp(sd of log value)`` (NaN for a linear one). ``pairs``: (i, j, correlation)
    with ``|correlation| > PAIR_CORRELATION``, strongest first; ``uninformed``: the indices
    whose ``share > UNINFORMED_SHARE``."""

    names: tuple[str, ...]
    laplace: Laplace
    best_scaled: np.ndarray
    low_scaled: np.ndarray
    high_scaled: np.ndarray
    clipped_low: np.ndarray
    clipped_high: np.ndarray
    share: np.ndarray
    best: np.ndarray
    low: np.ndarray
    high: np.ndarray
    sd: np.ndarray
    factor: np.ndarray
    log: np.ndarray
    pairs: tuple[tuple[int, int, float], ...]
    uninformed: tuple[int, ...]


def identifiability(names: list[str] | tuple[str, ...], scaling: Scaling,
                    best_scaled: np.ndarray, post: Laplace,
                    pair_correlation: float = PAIR_CORRELATION,
                    uninformed_share: float = UNINFORMED_SHARE) -> Identifiability:
    """Intervals, physical units, pairs and uninformed parameters of a :class:`Laplace`
    posterior centred on ``best_scaled`` (d,), for parameters ``names`` under ``scaling``."""
    u = np.clip(np.asarray(best_scaled, float), -1.0, 1.0)
    sd_u = post.sd
    half = Z95 * sd_u
    raw_lo, raw_hi = u - half, u + half
    lo_u, hi_u = np.maximum(raw_lo, -1.0), np.minimum(raw_hi, 1.0)
    share = (hi_u - lo_u) / 2.0
    width = 0.5 * (scaling.hi - scaling.lo)  # d(lo + (u + 1) width) / du, in value or log
    best = scaling.to_values(u)
    slope = np.where(scaling.log, best * width, width)
    sd = np.where(np.isfinite(sd_u), sd_u * slope, np.inf)
    factor = np.where(scaling.log, np.exp(np.minimum(sd_u * width, 700.0)), np.nan)
    d = len(names)
    pairs = sorted(((i, j, float(post.correlation[i, j])) for i in range(d)
                    for j in range(i + 1, d) if abs(post.correlation[i, j]) > pair_correlation),
                   key=lambda t: -abs(t[2]))
    return Identifiability(tuple(names), post, u, lo_u, hi_u, raw_lo < -1.0, raw_hi > 1.0,
                           share, best, scaling.to_values(lo_u), scaling.to_values(hi_u), sd,
                           factor, np.asarray(scaling.log, bool), tuple(pairs),
                           tuple(int(i) for i in np.flatnonzero(share > uninformed_share)))


# ------------------------------------------------------------------ a Jacobian from journaled calls
@dataclass(frozen=True)
class Stencil:
    """A forward-difference stencil among journaled points: the ``base`` point's index and,
    per coordinate k, the index of a run one step ``steps[k]`` along k alone (``runs`` (d,),
    ``steps`` (d,), scaled units); ``distance``: the base's from the point it stands for."""

    base: int
    runs: tuple[int, ...]
    steps: tuple[float, ...]
    distance: float


def find_stencil(points: np.ndarray, usable: np.ndarray, around: int,
                 max_step: float = MAX_STENCIL_STEP, max_distance: float = MAX_BASE_DISTANCE,
                 atol: float = 1e-9) -> Stencil | None:
    """The full stencil among ``points`` (m, d) (scaled coordinates; ``usable`` (m,) bool: a
    point with residuals) whose base is nearest to point ``around`` (itself first), within
    ``max_distance``: for each coordinate k a usable point that differs from the base in k
    alone, by ``0 < |step| <= max_step`` (the smallest step; the latest such point on a tie).
    None when no usable point within reach has one along every coordinate."""
    x = np.asarray(points, float)
    ok = np.asarray(usable, bool)
    dist = np.linalg.norm(x - x[around], axis=1)
    order = [i for i in np.argsort(dist, kind="stable") if ok[i] and dist[i] <= max_distance]
    if around in order:  # the point itself first
        order.remove(around)
        order.insert(0, around)
    d = x.shape[1]
    for b in order:
        delta = x - x[b]
        moved = np.abs(delta) > atol
        one = ok & (moved.sum(axis=1) == 1)
        runs, steps = [], []
        for k in range(d):
            cand = np.flatnonzero(one & moved[:, k] & (np.abs(delta[:, k]) <= max_step))
            if not cand.size:
                break
            h = np.abs(delta[cand, k])
            j = int(cand[np.flatnonzero(h == h.min())[-1]])
            runs.append(j)
            steps.append(float(delta[j, k]))
        else:
            return Stencil(int(b), tuple(runs), tuple(steps), float(dist[b]))
    return None


def stencil_jacobian(r_base: np.ndarray, r_runs: list[np.ndarray], steps) -> np.ndarray:
    """The forward-difference Jacobian (n, d): column k is ``(r_runs[k] - r_base) / steps[k]``
    (``r_base`` (n,), each ``r_runs[k]`` (n,))."""
    r0 = np.asarray(r_base, float)
    return np.column_stack([(np.asarray(rk, float) - r0) / h for rk, h in zip(r_runs, steps)])
