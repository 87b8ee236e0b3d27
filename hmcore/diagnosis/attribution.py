"""Attribution: which candidate extension explains the structured residual?

At the calibrated point the whitened residual vector is ``r`` (see
:class:`hmcore.scoring.observations.ObservationSet`). One finite-difference run per candidate
gives its sensitivity ``j = (r(probe) - r) / du``; the global parameters' sensitivities
``J_g`` come from the calibration. With the globals re-fitted jointly (their sensitivities
projected out, ``P = I - Q Q^T`` with ``Q`` an orthonormal basis of ``J_g``), the score test is

    score = (j_p^T r_p)^2 / (j_p^T j_p  r_p^T r_p),     j_p = P j,  r_p = P r,

the share of the residual sum of squares that the best linear step along the candidate removes,
and ``chi2 = (j_p^T r_p)^2 / (j_p^T j_p)`` is that reduction itself, in chi-square units
(whitened residuals: pure noise gives chi2 ~ chi-square with one degree of freedom). The step
is restricted to the candidate's bounds, so a fault that could only explain the data by being
*more* than fully open scores nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Score:
    """Score-test result of one candidate."""

    score: float
    chi2: float
    step_u: float
    """The best linear step in the candidate's scaled coordinate (within its bounds)."""
    unconstrained_step_u: float
    sensitivity_norm: float
    """|j_p|: how strongly the candidate moves the residual beyond what the globals can do."""

    def to_dict(self) -> dict:
        return {"score": self.score, "chi2": self.chi2, "step_u": self.step_u,
                "unconstrained_step_u": self.unconstrained_step_u,
                "sensitivity_norm": self.sensitivity_norm}


def projector_basis(J_global: np.ndarray | None, rtol: float = 1e-8) -> np.ndarray:
    """Orthonormal basis of the columns of ``J_global`` (zero columns dropped)."""
    if J_global is None or J_global.size == 0:
        return np.zeros((0 if J_global is None else J_global.shape[0], 0))
    U, s, _ = np.linalg.svd(J_global, full_matrices=False)
    if s.size == 0 or s[0] <= 0:
        return U[:, :0]
    return U[:, s > rtol * s[0]]


def project_out(Q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return v - Q @ (Q.T @ v) if Q.size else v


def score_test(r: np.ndarray, j: np.ndarray, Q: np.ndarray | None = None,
               step_bounds: tuple[float, float] = (-np.inf, np.inf)) -> Score:
    """Score of sensitivity ``j`` against residual ``r`` (globals' basis ``Q`` projected out).

    ``step_bounds`` limits the step ``t`` in ``r + t j`` (the candidate's room to its bounds).
    """
    r = np.asarray(r, float)
    j = np.asarray(j, float)
    if Q is not None and Q.size:
        r = project_out(Q, r)
        j = project_out(Q, j)
    rr = float(r @ r)
    jj = float(j @ j)
    if jj <= 1e-300 or rr <= 1e-300:
        return Score(0.0, 0.0, 0.0, 0.0, float(np.sqrt(max(jj, 0.0))))
    jr = float(j @ r)
    t_free = -jr / jj
    t = float(np.clip(t_free, *step_bounds))
    reduction = max(rr - float((r + t * j) @ (r + t * j)), 0.0)
    return Score(reduction / rr, reduction, t, t_free, float(np.sqrt(jj)))
