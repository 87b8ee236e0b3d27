"""A campaign on a case with ``[latent]``: its fields moved by the coefficients of their prior's
leading modes (:mod:`hmcore.fields.latent`, :mod:`hmcore.model.latent_case`).

``<campaign>/latent-basis/vN``: ``basis.parquet`` (one row per field value, ``parameter`` and
``cell`` as an ensemble's table labels them, ``mean`` and one column per mode, float64) and
``basis.json`` (the modes kept, the share of the prior's variance they hold, the modes the
prior had, the section, the prior's seeds, and the coefficients of the deck's own fields).
Drawn once: a rerun with the same case and code reuses the stored version. Every call of the
campaign then runs with :class:`hmcore.fields.members.LatentSimulator` bound to its
coefficients (:meth:`LatentSetup.simulator`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.calibration.calls import Job
from hmcore.fields.grid import FieldGrid, read_grid
from hmcore.fields.latent import LatentBasis
from hmcore.fields.layout import Layout
from hmcore.fields.members import LatentSimulator, ensemble_table
from hmcore.model.case import Case
from hmcore.model.latent_case import (
    deck_coefficients,
    latent_basis,
    latent_case,
    latent_layout,
)
from hmcore.scoring.evaluation import simulator_for
from hmcore.model.fingerprint import case_fingerprint
from storage import ArtifactStore, ArtifactVersion, code_version

LATENT_STEP = "latent-basis"
BASIS_FILE = "basis.parquet"
BASIS_DOC = "basis.json"


@dataclass(frozen=True, eq=False)
class LatentSetup:
    """The latent ``case`` (coefficients first in its space), the stored basis (``version``),
    the deck's ``grid``, the basis's ``layout`` and the coefficients of the deck's own fields
    (``deck``, the reference run "as given")."""

    case: Case
    version: ArtifactVersion
    grid: FieldGrid
    layout: Layout
    names: tuple[str, ...]
    deck: tuple[float, ...]

    def simulator(self, values: dict[str, float]) -> LatentSimulator:
        """The case's simulator running the fields of a call's coefficients."""
        z = [float(values[n]) for n in self.names]
        return LatentSimulator(simulator_for(self.case), self.version.file(BASIS_FILE),
                               self.case.fields, self.grid, self.layout,
                               self.case.info.keyword_names).bound(z)

    def job_simulator(self, job: Job) -> LatentSimulator:
        return self.simulator(job.values)


def latent_settings(case: Case) -> dict:
    """What a campaign's name is bound to besides its case artifact (which holds the scalar
    parameters only): the ``[latent]`` section, the fields and the prior ensemble's size and
    seed; {} for a case without ``[latent]`` (its settings as before)."""
    if case.latent is None:
        return {}
    return {"latent": {"section": case.latent.model_dump(mode="json"),
                       "fields": [f.model_dump(mode="json", by_alias=True)
                                  for f in case.fields],
                       "members": case.ensemble.size, "seed": case.ensemble.seed}}


@task(name="latent-basis", cache_policy=NO_CACHE)
def prepare_latent(case: Case, storage: str, campaign: str) -> LatentSetup:
    """Draw the case's prior ensemble, keep its leading modes (stored, reused on a rerun with
    the same case files, fields, ensemble size and seed and section) and give the case its
    coefficients, which the campaign then stores as its case (:func:`tasks.case.prepare_deck`)."""
    grid = read_grid(case.deck)
    layout = latent_layout(case, grid)
    inputs = {"case": case_fingerprint(case), "size": case.ensemble.size,
              "seed": case.ensemble.seed, "latent": case.latent.model_dump(mode="json"),
              "fields": [f.model_dump(mode="json", by_alias=True) for f in case.fields]}

    def write(directory: Path) -> None:
        basis = latent_basis(case, grid)
        rows = ensemble_table(basis.mean[None, :].astype("float32"), layout)[["parameter",
                                                                               "cell"]]
        basis.table(rows).to_parquet(directory / BASIS_FILE)
        doc = {"modes": basis.k, "share": basis.share, "available": basis.available,
               "members": case.ensemble.size, "seed": case.ensemble.seed,
               "latent": case.latent.model_dump(mode="json"),
               "deck_coefficients": [float(v) for v in deck_coefficients(case, grid, basis)]}
        (directory / BASIS_DOC).write_text(json.dumps(doc, indent=2) + "\n")

    version = ArtifactStore(storage).put(campaign, LATENT_STEP, inputs, write, code_version())
    doc = version.read_json(BASIS_DOC)
    basis = LatentBasis.from_table(version.read_parquet(BASIS_FILE), doc["share"],
                                   doc["available"])
    return LatentSetup(latent_case(case, basis), version, grid, layout, basis.names,
                       tuple(doc["deck_coefficients"]))

