"""What a campaign minimises and selects its best call by: the case's ``[misfit] objective``.

* ``likelihood`` (the default): the mean square of the noise-whitened residuals of the fitted
  history, ``chi2 / n``: each row's ``(simulated - observed) / sigma``, AR(1)-prewhitened along
  its series (:class:`~hmcore.scoring.observations.ObservationSet`), summed in squares and
  divided by ``n``, the rows whose residual is measurement noise
  (:meth:`~hmcore.scoring.observations.ObservationSet.n_noise`). A model that fits within the
  noise scores about 1; it is -2 log-likelihood per row, up to a constant, under the noise
  the campaign assumes.
* ``E``: the paper's misfit (:mod:`hmcore.scoring.misfit`), range-normalised mean squares of
  BHP, oil, water and gas.

Why the likelihood is the default: it weighs every row by its measurement error, so a response
measured precisely (a water cut of 1e-4 measured to 1e-6) counts as much as its information,
where E weighs each response by the square of its range and leaves GOR and water cut out; it
is what the default method (least squares on the whitened residuals) minimises, so the method
and the choice of the best call agree; and with the noise refined from the fit (below), the
truth is its minimum in expectation. ``E`` stays for comparison with the reference paper.

A call's value is a function of its record alone: a campaign's record keeps ``simulated``, the
simulated value of every row of the observation set, so its likelihood can be recomputed under
any noise. A record without it (a fake evaluator's, an older journal's) is scored by E, and by
its own ``residuals`` in a least-squares method.

What a method is told (:meth:`Objective.feedback`): under E exactly the record's reward
``-E - P`` (as before the objective existed); under the likelihood, a scored call's value times
``1 + P / E`` for a physics penalty ``P`` (so a penalty weighs against the value as it weighs
against E in the reward), and a failed call's penalty (failure penalty + P, in units of E)
times the value of a model that predicts zero everywhere (E = 1 is that model's E, so a
failure costs, relative to a zero prediction, what it costs under E). The least-squares
residuals (:meth:`Objective.residuals`) are the whitened ones under the likelihood and E's own
(``(simulated - observed) / (range * sqrt(n_c * n_categories))`` on the fitted rows of BHP,
oil, water and gas: their sum of squares is the mean variant's E; injection rates, which E
counts when observed, and the robust variant's worst well are not in them), each with one more
entry ``sqrt(P * ssr / E)`` for a penalty.

The prior of latent coefficients (a case's ``[latent]`` with ``prior = "regularised"``, the
default, under the likelihood): the coefficients ``z`` of the fields' modes are standard normal
a priori (:mod:`hmcore.fields.latent`), and ``sum z^2`` joins chi2 before the division by
``n`` (the likelihood is then -2 log-posterior per row), and ``z`` joins the least-squares
residuals: the fit is the coefficients' maximum a posteriori, not the fields that fit the
noise best. Under E there is no such term (E's scale is not the noise's): the bounds alone.

Refining the noise (:meth:`Objective.refined`): under the likelihood, where any fitted row's
sigma was estimated from the data (not given in the history's ``sigma`` column nor stated in
``[noise]``, which stay as they are), the noise is re-estimated from the residuals of a call
(:meth:`~hmcore.scoring.observations.ObservationSet.refine_simulated`);
:class:`~hmcore.calibration.calls.BudgetedCalls` decides when, from the best call so far.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from hmcore.calibration.methods.base import Feedback
from hmcore.fields.latent import prior_residuals
from hmcore.model.latent_case import latent_names
from hmcore.scoring.misfit import PRIMARY, category_ranges
from hmcore.scoring.observations import ObservationSet

OBJECTIVES = ("likelihood", "E")
DEFAULT_OBJECTIVE = "likelihood"
ESTIMATED_SOURCES = frozenset({"estimated", "pooled", "default", "floor"})
"""Sources of a row's sigma that the data gave (:mod:`hmcore.scoring.noise_fill`): the ones a
refinement may change."""
PRIMARY_OF = {q: c for c, q in PRIMARY.items()}


def feedback_of(record: dict) -> Feedback:
    """Reward and observed E (E, or the penalty of a failed run) from an evaluation record:
    what a method is told under the E objective."""
    E = record.get("E")
    scored = E is not None and math.isfinite(E)
    e_obs = E if scored else record["penalty"]
    worst = record.get("E_worst")
    return Feedback(float(record["reward"]), float(e_obs), scored,
                    float(record.get("penalty") or 0.0) if scored else 0.0,
                    float(worst) if scored and worst is not None and math.isfinite(worst)
                    else None)


def scored_E(record: dict) -> float | None:
    """A record's E when it was scored (None for a failed run)."""
    E = record.get("E")
    return float(E) if (E is not None and math.isfinite(E) and record.get("status") != "FAIL"
                        ) else None


@dataclass(frozen=True, eq=False)
class Objective:
    """The objective of a campaign (see the module docstring): ``name``, the observation set
    whose noise it assumes (``observations``; None: E from the records alone), the observed
    frame that set was made from and its context (to refine it), E's normalising ranges,
    which call's residuals the noise was refined from (``refined_from``, None: from the data),
    how many refinements made it, and the latent coefficients whose standard normal prior
    joins the likelihood (``prior``, see the module's docstring)."""

    name: str = "E"
    observations: ObservationSet | None = None
    observed: pd.DataFrame | None = None
    context: pd.DataFrame | None = None
    ranges: dict[str, float] = field(default_factory=dict)
    refined_from: int | None = None
    refinement: int = 0
    prior: tuple[str, ...] = ()
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        if self.name not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {self.name!r}")
        if self.name == "likelihood" and self.observations is None:
            raise ValueError("the likelihood objective needs the observation set")

    @classmethod
    def of_case(cls, case, observations: ObservationSet | None = None) -> Objective:
        """The case's objective over ``observations`` (default: the case's own set)."""
        obs = observations if observations is not None else ObservationSet.from_case(case)
        regularised = (case.misfit.objective == "likelihood" and case.latent is not None
                       and case.latent.prior == "regularised")
        return cls(case.misfit.objective, obs, case.informative, case.observed,
                   category_ranges(case.observed),
                   prior=latent_names(case) if regularised else ())

    @property
    def key(self) -> str:
        """The record key a consolidated record holds its value under."""
        return self.name

    @property
    def refinable(self) -> bool:
        """Whether refining can change anything: the likelihood, with a fitted row's sigma
        estimated from the data."""
        if self.name != "likelihood":
            return False
        rows = self.observations.rows
        idx = self.observations.vector_index("fit")
        return bool(np.isin(rows.sigma_source.to_numpy()[idx], list(ESTIMATED_SOURCES)).any())

    # ------------------------------------------------------------------ values
    def simulated(self, record: dict) -> np.ndarray | None:
        """The simulated value of every row the record keeps (None when it keeps none)."""
        sim = record.get("simulated")
        if sim is None or self.observations is None or record.get("status") == "FAIL":
            return None
        sim = np.array([np.nan if v is None else v for v in sim], float)
        return sim if sim.size == len(self.observations.rows) else None

    def whitened(self, simulated: np.ndarray) -> np.ndarray:
        obs = self.observations
        return obs.whiten((simulated - obs.rows.observed.to_numpy(float))
                          / obs.rows.sigma.to_numpy(float), "fit")

    def likelihood(self, record: dict) -> float:
        """``chi2 / n`` of a scored record under this noise (NaN without simulated values)."""
        sim = self.simulated(record)
        if sim is None or scored_E(record) is None:
            return float("nan")
        r = self.whitened(sim)
        z = prior_residuals(record.get("params") or {}, self.prior)
        return (float(r @ r) + float(z @ z)) / max(self.observations.n_noise("fit"), 1)

    def value(self, record: dict) -> float:
        """The record's value under the objective (NaN for a failed or unscored run)."""
        if self.name == "E":
            E = scored_E(record)
            return float("nan") if E is None else E
        return self.likelihood(record)

    @property
    def null_value(self) -> float:
        """The likelihood of a model predicting zero everywhere (the unit of a failure)."""
        if "null" not in self._cache:
            r = self.whitened(np.zeros(len(self.observations.rows)))
            self._cache["null"] = max(float(r @ r) / max(self.observations.n_noise("fit"), 1),
                                      1.0)
        return self._cache["null"]

    def cost(self, record: dict) -> float:
        """What a method minimises: the value, penalised (see the module docstring)."""
        return -self.feedback(record).reward

    def feedback(self, record: dict) -> Feedback:
        """What a proposer is told of a call."""
        if self.name == "E":
            return feedback_of(record)
        v, E = self.value(record), scored_E(record)
        P = float(record.get("penalty") or 0.0)
        if math.isfinite(v) and E is not None:
            cost = v * (1.0 + P / E) if P > 0 and E > 0 else v
            return Feedback(-cost, v, True, cost - v, None)
        cost = float(record.get("penalty") or 0.0) * self.null_value
        return Feedback(-cost, cost, False, 0.0, None)

    def residuals(self, record: dict) -> np.ndarray | None:
        """The least-squares residuals of a record (None for a failed run), with the penalty's
        entry."""
        if record.get("status") == "FAIL":
            return None
        sim = self.simulated(record)
        if sim is not None:
            r = (np.concatenate([self.whitened(sim),
                                 prior_residuals(record.get("params") or {}, self.prior)])
                 if self.name == "likelihood" else self._e_residuals(sim))
        elif record.get("residuals") is not None:  # a fake evaluator's or an older journal's
            r = np.nan_to_num(np.asarray(record["residuals"], float))
        else:
            return None
        P, E = float(record.get("penalty") or 0.0), scored_E(record)
        if P > 0 and E is not None and E > 0:
            return np.append(r, math.sqrt(P * float(r @ r) / E))
        return np.append(r, 0.0)

    def _e_residuals(self, simulated: np.ndarray) -> np.ndarray:
        idx, w = self._e_weights()
        d = simulated[idx] - self.observations.rows.observed.to_numpy(float)[idx]
        return np.nan_to_num(d * w)

    def _e_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """The fitted rows of E's categories and their weights ``1 / (range * sqrt(n_c * k))``."""
        if "e" not in self._cache:
            rows = self.observations.rows
            cat = rows.quantity.map(PRIMARY_OF).to_numpy(object)
            fit = (rows.period.to_numpy() == "fit") & pd.notna(cat)
            idx = np.flatnonzero(fit)
            cats = cat[idx]
            k = len(set(cats))
            counts = pd.Series(cats).value_counts().to_dict()
            w = np.array([1.0 / (self.ranges.get(c, 1.0) * math.sqrt(counts[c] * k))
                          for c in cats], float)
            self._cache["e"] = (idx, w)
        return self._cache["e"]

    # ------------------------------------------------------------------ choosing
    def best(self, records: list[dict]) -> dict | None:
        """The lowest-valued COMPLETE record (never INVALID or FAIL); None when none."""
        ok = [(v, r) for r in records if r.get("status") == "COMPLETE"
              and math.isfinite(v := self.value(r))]
        return min(ok, key=lambda t: t[0])[1] if ok else None

    def refined(self, record: dict) -> Objective:
        """This objective with the noise re-estimated from ``record``'s residuals (given and
        stated levels kept)."""
        sim = self.simulated(record)
        if sim is None or not self.refinable:
            raise ValueError(f"call {record.get('index')} cannot refine the noise")
        obs = self.observations.refine_simulated(sim, self.observed, self.context)
        return Objective(self.name, obs, self.observed, self.context, self.ranges,
                         int(record["index"]), self.refinement + 1, self.prior)

    def describe(self) -> dict:
        """The noise's provenance, for its stored artifact."""
        return {"objective": self.name, "refinement": self.refinement,
                "refined_from_call": self.refined_from,
                "rho": dict(self.observations.rho) if self.observations is not None else {},
                "n_noise": self.observations.n_noise("fit") if self.observations is not None
                else None, **({"prior": list(self.prior)} if self.prior else {})}
