"""Numerics of refitting the extended models: where each recalibration starts, which ones are
restarted from the deck's values, and the prior that keeps a restart near the model as given.

In the shape of :mod:`hmcore.diagnosis.recalibrate` (the bounded Levenberg-Marquardt of
:mod:`hmcore.calibration.least_squares` does the minimising): plain functions of coordinates,
residual sums of squares and settings; nothing here runs the simulator.
:class:`hmcore.diagnosis.workflow.Diagnosis` makes the runs.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from hmcore.calibration.least_squares import LMSettings
from hmcore.diagnosis.settings import DiagnosisSettings


def capped(lm: LMSettings, evaluations: int) -> LMSettings:
    """``lm`` with at most ``evaluations`` evaluations (never fewer than none)."""
    return dataclasses.replace(lm, max_evaluations=min(lm.max_evaluations, max(evaluations, 0)))


# ----------------------------------------------------------------------------- line search
def joint_direction(J_global: np.ndarray, free: np.ndarray, sensitivity: np.ndarray
                    ) -> np.ndarray:
    """Direction (scaled coordinates: globals + the candidate) along which the linear model
    moves the candidate by one unit while the free globals undo what they had absorbed of it:
    ``-pinv(J_globals) j_candidate`` per unit; globals held at a bound stay."""
    direction = np.zeros(J_global.shape[1] + 1)
    direction[-1] = 1.0
    if free.any():
        direction[:-1][free] = -np.linalg.lstsq(J_global[:, free], sensitivity, rcond=None)[0]
    return direction


def line_search_points(base_u: np.ndarray, step: float, direction: np.ndarray,
                       factors: tuple[float, ...], taken: list[np.ndarray]) -> list[np.ndarray]:
    """Points ``base_u + f * step * direction`` (clipped to the box) for each multiple ``f`` of
    the score test's linear ``step``, skipping any within 1e-3 of a point already ``taken``
    (which grows with the new points)."""
    out = []
    for f in factors:
        u = np.clip(base_u + f * step * direction, -1.0, 1.0)
        if all(np.max(np.abs(u - v)) > 1e-3 for v in taken):
            taken.append(u)
            out.append(u)
    return out


def line_search_affordable(left: int | None, n_jobs: int, n_candidates: int, dim: int) -> bool:
    """Whether the line search's ``n_jobs`` runs leave enough of the budget (``left`` calls,
    None: no budget) for the recalibrations: twice the line search and a Jacobian's worth per
    candidate."""
    return n_jobs > 0 and (left is None or left >= 2 * n_jobs + n_candidates * dim)


# ----------------------------------------------------------------------------- restarts
def restart_choice(warm_ssr: dict[int, float], base_ssr: float,
                   s: DiagnosisSettings) -> list[int]:
    """Which warm-started recalibrations (index -> fitted SSR of the best point) to restart
    from the deck's values: the ``s.restart_top`` best, and every other one within
    ``s.tie_band`` of the best fit whose fit beats the calibrated base (``base_ssr``) by more
    than ``s.fit_threshold``; at most ``s.restart_max``. Best fits first."""
    order = sorted(warm_ssr, key=lambda k: warm_ssr[k])
    if not order:
        return []
    best = warm_ssr[order[0]]
    return [k for j, k in enumerate(order) if j < s.restart_top or (
        warm_ssr[k] <= best + s.tie_band and base_ssr - warm_ssr[k] > s.fit_threshold)
            ][: max(s.restart_max, s.restart_top)]


def veto_restart_choice(warm_ssr: dict[int, float], heldout_ok: dict[int, bool],
                        base_ssr: float, s: DiagnosisSettings) -> list[int]:
    """Which warm-started recalibrations (index -> fitted SSR of the best point; whether the
    held-back history plainly confirms it: E and SSR both lower) to restart from the deck's
    values when no global is at its bound: those that fit beyond noise (beat ``base_ssr`` by
    more than ``s.fit_threshold``) but that the held-back history does not plainly confirm,
    and only while they could still outrank the best confirmed fit (within ``s.tie_band`` of
    it or better); at most ``s.restart_max``, best
    fits first. A fit the held-back history vetoes has usually settled in a basin the globals
    made (PUNQ-S3, a box around PRO-4 x3.5: the globals went to poro 0.86, permy 1.81, permz
    0.53, none at a bound; the box fitted best and predicted worst)."""
    order = sorted(warm_ssr, key=lambda k: warm_ssr[k])
    confirmed = [warm_ssr[k] for k in order if heldout_ok.get(k)
                 and base_ssr - warm_ssr[k] > s.fit_threshold]
    ceiling = confirmed[0] + s.tie_band if confirmed else math.inf
    return [k for k in order if not heldout_ok.get(k) and base_ssr - warm_ssr[k] > s.fit_threshold
            and warm_ssr[k] <= ceiling][: s.restart_max]


def restart_grid(grid: tuple[float, ...], recalibrated: float | None) -> list[float]:
    """The candidate's values (scaled) tried with the globals at the deck's values before a
    restart: ``grid`` and the recalibrated value, none within 0.02 of an earlier one."""
    seen: list[float] = []
    for g in list(grid) + ([recalibrated] if recalibrated is not None else []):
        if all(abs(g - x) > 0.02 for x in seen):
            seen.append(g)
    return seen


def restart_evaluations(left: int, n_restarts: int, grid_size: int, dim: int) -> int | None:
    """Evaluations each of ``n_restarts`` restarts may take of ``left`` calls, after its grid
    and its check run (two calls set aside); None when that is less than a Jacobian and a few
    steps (``dim + 3``): the restarts are skipped."""
    per = left // n_restarts - 2 - grid_size
    return per if per >= dim + 3 else None


@dataclass(frozen=True)
class GlobalsPrior:
    """Gaussian prior on the globals (the first ``len(centre)`` scaled coordinates) at the
    deck's values ``centre`` with standard deviation ``sd``: its residuals extend a run's."""

    centre: np.ndarray
    sd: float

    def residuals(self, u: np.ndarray) -> np.ndarray:
        return (u[: self.centre.size] - self.centre) / self.sd

    def value(self, u: np.ndarray) -> float:
        p = self.residuals(u)
        return float(p @ p)

    def extend(self, u: np.ndarray, r: np.ndarray | None) -> np.ndarray | None:
        """``r`` followed by the prior's residuals at ``u`` (None for a failed run)."""
        return None if r is None else np.concatenate([r, self.residuals(u)])
