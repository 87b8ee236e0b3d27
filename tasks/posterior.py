"""A campaign's forecast members from its posterior: parameter sets drawn from the Laplace
posterior at its best call (:mod:`hmcore.calibration.posterior`), simulated after the fit,
apart from the budget.

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
from hmcore.reporting.identifiability import load_identifiability
from storage import ArtifactStore, ArtifactVersion, code_version, to_jsonable
from tasks.simulate import Destination

POSTERIOR_STEP = "posterior"
POSTERIOR_RUNS = "posterior-runs"
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


def journal_name(version: int) -> str:
    """The journal of the runs of the ``posterior`` artifact's version ``version``."""
    return f"{POSTERIOR_STEP}-{version:04d}"


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
    inputs = {"results": results.ref() if results is not None else None, "count": count,
              "seed": seed}
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
    stencil = found.stencil
    doc = {"best_call": found.best_index + 1, "asked": count, "kept": len(jobs),
           "tried": draws.tried, "inflation": draws.inflation, "s2": found.result.laplace.s2,
           "free": [found.result.names[i] for i in draws.free],
           "stencil": {"base_call": stencil.base + 1,
                       "runs": [j + 1 for j in stencil.runs]} if stencil else None,
           "draws": [{"draw": k + 1, "action": list(j.action), "values": j.values}
                     for k, j in enumerate(jobs)],
           "reason": "" if jobs else "The box held none of the posterior's draws."}
    version = store.put(campaign, POSTERIOR_STEP, inputs, lambda d: _write(d, doc),
                        code_version())
    return PosteriorPlan(jobs, version, doc["reason"])


def _write(directory: Path, doc: dict) -> None:
    (directory / "draws.json").write_text(json.dumps(to_jsonable(doc, "draws.json"), indent=1,
                                                     sort_keys=True))
