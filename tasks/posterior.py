"""A campaign's forecast members from its posterior: parameter sets drawn from the Laplace
posterior at its best call (:mod:`hmcore.calibration.posterior`), simulated after the fit,
apart from the budget; and, first, the finite-difference runs that posterior needs when the
method left no Jacobian at the best call (:func:`plan_jacobian`: one per parameter, in the
journal ``jacobian-<best call>``, run directories in ``jacobian-runs/``).

``<campaign>/posterior/vN``: ``draws.json`` (the best call the draws stand on, the stencil
of its Jacobian, the inflation, the draws asked for and kept, the parameters the data leave
free, and each draw's scaled point and values) or, when there is no posterior to draw from,
the reason. Version N's runs go to the campaign's journal ``posterior-NNNN``
(``evaluations-posterior-NNNN/``, run directories ``posterior-runs/NNNN-<index:06d>``): a
resumed campaign with the same results draws the same points into the same version and
simulates only those not yet journaled; other results (a longer budget) draw anew, into a
new version and journal. The forecast (:mod:`tasks.curves`) is made of the latest version's
valid runs.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.calibration.calls import Job, PhysicsPrecheck
from hmcore.calibration.posterior import laplace_draws
from hmcore.model.case import Case
from hmcore.reporting.identifiability import call_label, jacobian_journal, load_identifiability
from storage import ArtifactStore, ArtifactVersion, code_version, to_jsonable
from storage.posterior import POSTERIOR_STEP, journal_name
from tasks.simulate import Destination

POSTERIOR_RUNS = "posterior-runs"
JACOBIAN_RUNS = "jacobian-runs"
PHASE = "posterior-draw"
STREAM = 0x504F5354  # "POST": the draws' own stream of the campaign's seed


@dataclass(frozen=True)
class PosteriorPlan:
    """The draws to simulate (``jobs``, index 0..m-1 in :attr:`destination`'s journal) and
    the stored ``posterior`` artifact describing them; ``reason`` when there are none."""

    jobs: tuple[Job, ...]
    version: ArtifactVersion
    reason: str = ""

    @property
    def destination(self) -> Destination:
        return destination(self.version.version)


def destination(version: int) -> Destination:
    """Where the runs of the ``posterior`` artifact's version ``version`` go."""
    return Destination(journal=journal_name(version), runs=POSTERIOR_RUNS,
                       run_name=f"{version:04d}-" + "{index:06d}")


@task(name="draw-posterior", cache_policy=NO_CACHE)
def draw_posterior(case: Case, store_root: str, campaign: str, seed: int,
                   count: int) -> PosteriorPlan:
    """Draw ``count`` parameter sets from the posterior at the campaign's best call (from its
    consolidated results: :func:`hmcore.reporting.identifiability.load_identifiability`), each
    within the box and passing the physics checks its values decide alone; store what was
    drawn and why. No draws (``reason``) when the campaign has no Jacobian at its best call."""
    store = ArtifactStore(store_root)
    found = load_identifiability(store, campaign)
    results = store.latest(campaign, "results")
    stencil = found.stencil if found is not None else None
    inputs = {"results": results.ref() if results is not None else None, "count": count,
              "seed": seed, "stencil": None if stencil is None else
              {"base": stencil.base, "runs": list(stencil.runs)}}  # the posterior it stands on
    if found is None or found.result is None:
        reason = (found.reason if found is not None else "The campaign has no results.")
        version = store.put(campaign, POSTERIOR_STEP, inputs,
                            lambda d: _write(d, {"draws": [], "reason": reason}),
                            code_version())
        return PosteriorPlan((), version, reason)
    space, precheck = case.space, PhysicsPrecheck.of(case)

    def valid(points: np.ndarray) -> np.ndarray:
        return np.array([not precheck(space.to_values(u)) for u in points], bool)

    draws = laplace_draws(found.result, count, np.random.default_rng([seed, STREAM]), valid)
    jobs = tuple(Job(k, space.to_values(u), tuple(float(x) for x in u), 0, PHASE)
                 for k, u in enumerate(draws.points))
    doc = {"best_call": found.best_index + 1, "asked": count, "kept": len(jobs),
           "tried": draws.tried, "inflation": draws.inflation, "s2": found.result.laplace.s2,
           "free": [found.result.names[i] for i in draws.free],
           "stencil": {"base_call": stencil.base + 1,
                       "runs": [call_label(j) for j in stencil.runs]} if stencil else None,
           "draws": [{"draw": k + 1, "action": list(j.action), "values": j.values}
                     for k, j in enumerate(jobs)],
           "reason": "" if jobs else "The box held none of the posterior's draws."}
    version = store.put(campaign, POSTERIOR_STEP, inputs, lambda d: _write(d, doc),
                        code_version())
    return PosteriorPlan(jobs, version, doc["reason"])


def _write(directory: Path, doc: dict) -> None:
    (directory / "draws.json").write_text(json.dumps(to_jsonable(doc, "draws.json"), indent=1,
                                                     sort_keys=True))


STEP = 0.05
"""The Jacobian's finite-difference step after the fit, in scaled units (2.5 % of a range;
within :data:`hmcore.scoring.identifiability.MAX_STENCIL_STEP`)."""


@dataclass(frozen=True)
class JacobianPlan:
    """The finite-difference runs a campaign's best call still needs for its posterior
    (``jobs``, one per parameter, into :attr:`destination`); none when its calls hold a
    stencil there, or it has no valid call."""

    jobs: tuple[Job, ...]
    best_index: int | None

    @property
    def destination(self) -> Destination:
        return Destination(journal=jacobian_journal(self.best_index), runs=JACOBIAN_RUNS,
                           run_name=f"{self.best_index + 1:06d}-" + "{index:02d}")



@task(name="plan-jacobian", cache_policy=NO_CACHE)
def plan_jacobian(case: Case, store_root: str, campaign: str) -> JacobianPlan:
    """One forward step of :data:`STEP` along each parameter from the best call (backward
    where forward would leave the box or break a physics check its values decide), when the
    campaign's calls hold no stencil there (:func:`load_identifiability`): the runs a
    posterior needs that the method did not make (a campaign ended mid-descent, a method
    without derivatives), simulated apart from the budget."""
    store = ArtifactStore(store_root)
    found = load_identifiability(store, campaign)
    if found is None or found.result is not None or found.best_index is None:
        return JacobianPlan((), None if found is None else found.best_index)
    results = store.latest(campaign, "results")
    best = next(r for r in results.read_json("records.json")["records"]
                if r["index"] == found.best_index)
    space, precheck = case.space, PhysicsPrecheck.of(case)
    u = np.asarray(best["action"], float)
    jobs = []
    for k in range(space.dim):
        for step in ((STEP, -STEP) if u[k] + STEP <= 1.0 else (-STEP, STEP)):
            x = u.copy()
            x[k] += step
            if abs(x[k]) <= 1.0 and not precheck(space.to_values(x)):
                break
        jobs.append(Job(k, space.to_values(x), tuple(float(v) for v in x), 0, "jacobian"))
    return JacobianPlan(tuple(jobs), found.best_index)
