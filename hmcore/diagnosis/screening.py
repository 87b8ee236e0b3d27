"""Screening: rank the candidate extensions by a score test at the calibrated point.

The ranking needs one finite-difference ("probe") run per candidate, and one per global
parameter when the calibration left no finite-difference Jacobian of the globals close enough
to reuse. :func:`probe_jobs` says which runs to make; :func:`screen` turns their whitened
residual vectors into projected score tests (:mod:`hmcore.diagnosis.attribution`) and the
ranking document; :func:`confirm_choice` picks the screened candidates worth an actual
recalibration. The simulator is never run here: the workflow makes the runs and hands over
their residual vectors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hmcore.diagnosis.attribution import Score, projector_basis, score_test
from hmcore.diagnosis.candidate import Candidate
from hmcore.diagnosis.recalibrate import Coordinates
from hmcore.diagnosis.settings import DiagnosisSettings


@dataclass(frozen=True)
class ProbeJob:
    """One run of the ranking: a global parameter's finite difference (``index``, ``step``
    in scaled coordinates) or a candidate's probe."""

    values: dict[str, float]
    candidate: Candidate | None = None
    index: int = -1
    step: float = 0.0


def probe_jobs(coords: Coordinates, u_base: np.ndarray, values: dict[str, float],
               candidates: list[Candidate], need_globals: bool, fd_step: float
               ) -> list[ProbeJob]:
    """The ranking's runs: a finite difference per global (``need_globals``: no Jacobian of
    the globals to reuse; the step goes down at the upper bound), then a probe per candidate
    (the calibrated ``values`` with the candidate at its probe value)."""
    jobs = []
    if need_globals:
        for i in range(coords.dim):
            h = fd_step if u_base[i] + fd_step <= 1 else -fd_step
            u = u_base.copy()
            u[i] += h
            jobs.append(ProbeJob(coords.to_values(u), index=i, step=h))
    jobs += [ProbeJob({**values, c.name: c.probe}, candidate=c) for c in candidates]
    return jobs


def global_jacobian(r0: np.ndarray, jobs: list[ProbeJob], residuals: list[np.ndarray | None],
                    dim: int) -> np.ndarray:
    """Forward-difference Jacobian of the whitened residuals in the globals (a failed run
    leaves its column at zero)."""
    J = np.zeros((r0.size, dim))
    for job, r in zip(jobs, residuals):
        if job.candidate is None and r is not None:
            J[:, job.index] = (r - r0) / job.step
    return J


def held_at_bounds(J_global: np.ndarray, r0: np.ndarray, u_base: np.ndarray) -> np.ndarray:
    """Globals pressed against a bound (at it, the gradient pointing outwards): they cannot
    take over a candidate's step, so the score test does not project them out."""
    g = J_global.T @ r0
    return ((u_base >= 1 - 1e-6) & (g < 0)) | ((u_base <= -1 + 1e-6) & (g > 0))


@dataclass(frozen=True)
class Screening:
    """The score tests of the candidates, their sensitivities and the ranking document."""

    scores: dict[str, Score] = field(default_factory=dict)
    sensitivity: dict[str, np.ndarray] = field(default_factory=dict)
    document: dict = field(default_factory=dict)


def screen(candidates: list[Candidate], jobs: list[ProbeJob], residuals: list[np.ndarray | None],
           reasons: list[str], r0: np.ndarray, J_global: np.ndarray, held: np.ndarray,
           global_names: list[str], s: DiagnosisSettings) -> Screening:
    """Score test of each probed candidate (``residuals``: the probe runs' whitened residual
    vectors, None for a failed run with its ``reasons``), the globals that are not held at a
    bound projected out; candidates ordered by chi2, those beyond ``s.chi2_threshold`` and
    those screened for recalibration (``s.screen_threshold``)."""
    Q = projector_basis(J_global[:, ~held])
    scores: dict[str, Score] = {}
    sensitivity: dict[str, np.ndarray] = {}
    rows: list[dict[str, Any]] = []
    for job, r, reason in zip(jobs, residuals, reasons):
        c = job.candidate
        if c is None:
            continue
        cc = Coordinates([c.parameter])
        u0 = float(cc.to_u({c.name: c.neutral})[0])
        du = float(cc.to_u({c.name: c.probe})[0]) - u0
        if r is None or abs(du) < 1e-12:
            rows.append({"id": c.id, "status": "probe run failed", "reason": reason})
            continue
        j = (r - r0) / du
        sensitivity[c.id] = j
        sc = score_test(r0, j, Q, (-1.0 - u0, 1.0 - u0))
        scores[c.id] = sc
        raw = score_test(r0, j, None, (-1.0 - u0, 1.0 - u0))
        rows.append({"id": c.id, "status": "ok", **sc.to_dict(),
                     "score_without_refit": raw.score, "chi2_without_refit": raw.chi2,
                     "u_neutral": u0, "u_probe": u0 + du,
                     "predicted_value": cc.to_values(np.array([u0 + sc.step_u]))[c.name]})
    order = sorted(scores, key=lambda k: -scores[k].chi2)
    beyond = [k for k in order if scores[k].chi2 >= s.chi2_threshold]
    screened = [k for k in order if scores[k].chi2 >= min(s.screen_threshold, s.chi2_threshold)]
    by_id = {c.id: c for c in candidates}
    document = {
        "chi2_threshold": s.chi2_threshold, "ssr_fit": float(r0 @ r0), "n_fit": int(r0.size),
        "globals_held_at_bounds": [n for n, h in zip(global_names, held) if h],
        "order": order, "beyond_noise": beyond, "screen_threshold": s.screen_threshold,
        "screened": screened,
        "candidates": [{**by_id[row["id"]].machine(), "description":
                        by_id[row["id"]].description, **row} for row in rows],
        "runs": len(jobs)}
    return Screening(scores, sensitivity, document)


def confirm_choice(screened: list[tuple[str, float]], s: DiagnosisSettings) -> list[str]:
    """Which screened candidates (id, score-test chi2; best first) to recalibrate: the
    ``s.confirm_top`` first, and more up to ``s.confirm_max`` while they reach
    ``s.confirm_close`` of the leader's chi2; every one up to ``s.confirm_weak_max`` when the
    leader's chi2 is under ``s.weak_lead`` (the linear ranking is not to be trusted there)."""
    if not screened:
        return []
    ids = [k for k, _ in screened]
    lead = screened[0][1]
    if lead < s.weak_lead:
        return ids[: max(s.confirm_top, s.confirm_weak_max)]
    return ids[: s.confirm_top] + [k for k, chi2 in screened[s.confirm_top: s.confirm_max]
                                   if chi2 >= s.confirm_close * lead]
