"""Explanations ranked by their support in the data: a log evidence per explanation, the
weights it gives, and the answer (one cause, or the set the data cannot separate).

Every explanation of a diagnosis - ``none`` (the calibrated model), each recalibrated
candidate (the globals + its parameter), ``unexplained`` (the calibrated model + a free bias
where the residual analysis finds one beyond noise) - is a least-squares fit of the same
whitened residuals ``r`` (standard normal under the noise model). Its log evidence is the
Laplace approximation (MacKay 1992, "Bayesian interpolation", Neural Computation 4:415;
Kass & Raftery 1995, "Bayes factors", JASA 90:773, section 4.1.1) at the fit::

    log Z = -SSR_fit / 2  +  log Occam,
    log Occam = -1/2 log det(I + (w^2 / 2 pi) J^T J)

with ``J`` the Jacobian of the whitened fitted residuals in the scaled coordinates ``u`` (each
parameter's range is [-1, 1], width ``w = 2``). The uniform prior over a parameter's range is
replaced by the Gaussian of the same height at its centre (variance ``w^2 / 2 pi``): a
direction the data pin down costs ``log(posterior width / prior width)`` as in MacKay's Occam
factor, and a direction they do not constrain costs nothing (the uniform prior's Laplace
approximation would give it an infinite reward). That Gaussian's pull towards the centre
(``u^2 pi / w^2``, at most pi/4 nats inside the range) is not added: the uniform prior it
stands for has none. The constant ``-N/2 log 2 pi`` is the same
for every explanation (the same data) and is dropped. Where an explanation has parameters
without a Jacobian (``unexplained``'s biases: no simulation moves them), each costs
``1/2 log n`` (the BIC, Schwarz 1978; Kass & Raftery 1995 section 4.1.3: the Laplace
approximation under a unit-information prior).

The held-back history is data too: the score adds its predictive log likelihood at the fit,
``-SSR_heldout / 2`` (a plug-in prequential term: ``log p(fit, held) = log p(fit) +
log p(held | fit)``), so that a model that fits as well but predicts worse loses weight.

When even the best explanation leaves more than noise (reduced chi-square ``s = min SSR / n``
above 1) the noise model is too tight and every SSR difference would be over-read: all SSRs
and curvatures are divided by ``s`` (a variance inflation, the quasi-likelihood's dispersion).

Weights are the softmax of the log evidences (equal prior on every explanation). The answer
is the smallest set of explanations, best first, whose weights add up to ``mass`` (0.9):
one cause when its own weight reaches it - then its Bayes factor over the next is at least
``0.9 / 0.1 = 9``, "strong" on Jeffreys' scale (10) and 2 ln B = 4.4, "positive" bordering
"strong" on Kass & Raftery's - otherwise the set, which the data cannot separate.

Pure numpy; nothing here simulates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

PRIOR_WIDTH = 2.0
"""Width of every parameter's prior range in scaled coordinates ([-1, 1])."""
MASS = 0.9
"""Weight the answer's set must carry (one cause when its own weight reaches it)."""


class EvidenceMethod(str, Enum):
    """How an explanation's Occam factor was computed."""

    LAPLACE = "laplace"
    """From the Jacobian of its fit (every parameter simulated)."""
    LAPLACE_BIC = "laplace+bic"
    """The Jacobian for the simulated parameters, the BIC for the others."""
    BIC = "bic"
    """No Jacobian: the BIC for every parameter."""


class AnswerKind(str, Enum):
    """One dominant explanation, or a set the data cannot separate."""

    SINGLE = "single"
    SET = "set"


@dataclass(frozen=True)
class Fit:
    """One explanation's fit of the whitened residuals."""

    id: str
    kind: str
    """The candidate's family, ``none`` or ``unexplained``."""
    ssr_fit: float
    """Whitened SSR of the fitted history at the fit."""
    ssr_heldout: float
    """Whitened SSR of the held-back history predicted by the fit."""
    jtj_eigenvalues: np.ndarray
    """Shape (k,): eigenvalues of J^T J, J the (n_fit, k) Jacobian of the whitened fitted
    residuals in scaled coordinates, for the k parameters with one (may be empty)."""
    n_bic: int = 0
    """Parameters without a Jacobian: each costs 1/2 log n_fit."""
    log_prior: float = 0.0
    """Log prior weight relative to the others (``unexplained``: where it acts, chosen)."""
    fit_E: float | None = None
    heldout_E: float | None = None

    @property
    def n_parameters(self) -> int:
        return len(self.jtj_eigenvalues) + int(self.n_bic)

    @property
    def method(self) -> EvidenceMethod:
        if self.n_bic == 0:
            return EvidenceMethod.LAPLACE
        return EvidenceMethod.BIC if len(self.jtj_eigenvalues) == 0 else \
            EvidenceMethod.LAPLACE_BIC


@dataclass(frozen=True)
class Scored:
    """An explanation with its log evidence (in nats, up to a constant shared by all) and
    weight."""

    fit: Fit
    log_likelihood: float
    """``-(SSR_fit + SSR_heldout) / (2 s)``."""
    log_occam: float
    log_evidence: float
    weight: float


@dataclass(frozen=True)
class Ranked:
    """The explanations best first and the answer."""

    items: tuple[Scored, ...]
    kind: AnswerKind
    members: tuple[str, ...]
    """Ids of the answer: one, or the set carrying ``mass``."""
    bayes_factor: float
    """Of the first over the second (inf: one explanation)."""
    scale: float
    """The variance inflation ``s`` applied (1: the noise model as it is)."""
    mass: float

    @property
    def weights(self) -> dict[str, float]:
        return {x.fit.id: x.weight for x in self.items}


def log_occam(eigenvalues: np.ndarray, scale: float = 1.0,
              prior_width: float = PRIOR_WIDTH) -> float:
    """``-1/2 sum log(1 + w^2 / (2 pi) * lambda / s)`` over ``eigenvalues`` (shape (k,), of
    J^T J): the Laplace Occam factor under the Gaussian of the uniform prior's height. Negative
    eigenvalues (round-off) count as 0."""
    lam = np.clip(np.asarray(eigenvalues, float), 0.0, None) / float(scale)
    return float(-0.5 * np.sum(np.log1p(prior_width ** 2 / (2.0 * math.pi) * lam)))


def bic_occam(k: int, n: int) -> float:
    """``-k/2 log n``: the BIC's cost of ``k`` parameters fitted to ``n`` points."""
    return -0.5 * k * math.log(max(n, 2))


def jtj_eigenvalues(jacobian: np.ndarray | None) -> np.ndarray | None:
    """Shape (k,): the eigenvalues of J^T J of an (n, k) Jacobian (None: None; a non-finite
    Jacobian: None)."""
    if jacobian is None:
        return None
    J = np.asarray(jacobian, float)
    if J.ndim != 2 or not np.all(np.isfinite(J)):
        return None
    return np.linalg.eigvalsh(J.T @ J)


def softmax(log_evidence: np.ndarray) -> np.ndarray:
    """Shape (m,) -> (m,): ``exp(l - max) / sum``; -inf gets 0 (all -inf: equal weights)."""
    x = np.asarray(log_evidence, float)
    if not np.isfinite(np.max(x)):
        return np.full(x.shape, 1.0 / x.size)
    e = np.exp(x - np.max(x))
    return e / e.sum()


def rank(fits: list[Fit] | tuple[Fit, ...], n_fit: int, mass: float = MASS,
         prior_width: float = PRIOR_WIDTH, heldout: bool = True) -> Ranked:
    """Score, weigh and rank ``fits`` (see the module docstring); ``n_fit``: measured fitted
    points (the variance inflation's and the BIC's n); ``heldout``: add the held-back
    predictive term. Non-finite SSRs (a failed fit) get weight 0."""
    if not fits:
        raise ValueError("no explanation to rank")
    ok = [f for f in fits if math.isfinite(f.ssr_fit)]
    n = max(int(n_fit), 1)
    scale = max(1.0, min((f.ssr_fit for f in ok), default=n) / n)
    logs = []
    for f in fits:
        ssr = f.ssr_fit + (f.ssr_heldout if heldout and math.isfinite(f.ssr_heldout) else 0.0)
        ll = -0.5 * ssr / scale if math.isfinite(f.ssr_fit) else -math.inf
        occ = log_occam(f.jtj_eigenvalues, scale, prior_width) + bic_occam(f.n_bic, n)
        logs.append((ll, occ, ll + occ + f.log_prior))
    w = softmax(np.array([x[2] for x in logs]))
    scored = sorted((Scored(f, ll, occ, le, float(wi))
                     for f, (ll, occ, le), wi in zip(fits, logs, w)),
                    key=lambda s: -s.log_evidence)
    members, total = [], 0.0
    for s in scored:
        members.append(s.fit.id)
        total += s.weight
        if total >= mass:
            break
    bf = (math.inf if len(scored) == 1 else
          math.exp(min(scored[0].log_evidence - scored[1].log_evidence, 700.0)))
    return Ranked(tuple(scored), AnswerKind.SINGLE if len(members) == 1 else AnswerKind.SET,
                  tuple(members), bf, float(scale), float(mass))
