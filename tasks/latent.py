"""A campaign on a case with ``[latent]``: its fields moved by the coefficients of their prior's
leading modes (:mod:`hmcore.fields.latent`, :mod:`hmcore.model.latent_case`).

``<campaign>/latent-basis/vN`` (:mod:`storage.latent`).
Drawn once: a rerun with the same inputs reuses the stored version, whatever code made it, and
the campaign's name is bound to its hash (:func:`latent_settings`). Every call of the
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
from storage import ArtifactStore, ArtifactVersion, code_version, sha256_json, to_jsonable
from storage.latent import BASIS_DOC, BASIS_FILE, LATENT_STEP



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

    @property
    def floor(self) -> dict[str, float]:
        """The reference run "as given": the coefficients of the deck's own fields."""
        return dict(zip(self.names, self.deck, strict=True))


def reference_runs(setup: LatentSetup | None) -> dict:
    """The keyword arguments of :func:`tasks.reference.run_references` for a campaign or a
    benchmark on a latent case (its floor and its calls' simulator); {} for any other."""
    if setup is None:
        return {}
    return {"floor": setup.floor, "simulator_of": setup.job_simulator}


def latent_settings(case: Case, setup: LatentSetup | None = None) -> dict:
    """What a campaign's name (and its reference journal's) is bound to besides its case
    artifact: the ``[latent]`` section, the fields, the prior ensemble's size and seed and,
    with ``setup``, the stored basis's hash (so that a resumed campaign reads its journaled
    coefficients in the basis they were made in); {} for a case without ``[latent]``."""
    if case.latent is None:
        return {}
    bound = {"section": case.latent.model_dump(mode="json"),
             "fields": [f.model_dump(mode="json", by_alias=True) for f in case.fields],
             "members": case.ensemble.size, "seed": case.ensemble.seed}
    if setup is not None:
        bound["basis_sha256"] = setup.version.manifest["files"][BASIS_FILE]["sha256"]
    return {"latent": bound}


def latent_conflict(storage: str, campaign: str, case: Case) -> str | None:
    """One line when ``campaign`` is bound to other latent settings than ``case``'s (another
    section, fields or prior, or none): checked before the basis is drawn into it."""
    stored = ArtifactStore(storage).settings(campaign)
    if stored is None:
        return None
    before = dict(stored.get("latent") or {})
    before.pop("basis_sha256", None)
    now = latent_settings(case).get("latent") or {}
    if before == now:
        return None
    if not before or not now:
        return (f"campaign '{campaign}' in {storage} was started "
                f"{'with' if before else 'without'} a [latent] section and the case has "
                f"{'none' if before else 'one'}; choose another --campaign name")
    diff = sorted(k for k in set(before) | set(now) if before.get(k) != now.get(k))
    return (f"campaign '{campaign}' in {storage} was started with other latent settings "
            f"({', '.join(diff)} differ); set them back or choose another --campaign name")


def _stored_basis(store: ArtifactStore, campaign: str, inputs: dict) -> ArtifactVersion | None:
    """The newest intact basis made from ``inputs``, whatever code made it: a resumed
    campaign keeps the basis it started with."""
    wanted = sha256_json(to_jsonable(inputs, "inputs"))
    for version in reversed(store.versions(campaign, LATENT_STEP)):
        if version.manifest.get("inputs_hash") == wanted and not version.verify():
            return version
    return None


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

    store = ArtifactStore(storage)
    version = _stored_basis(store, campaign, inputs) or store.put(campaign, LATENT_STEP, inputs,
                                                                   write, code_version())
    doc = version.read_json(BASIS_DOC)
    basis = LatentBasis.from_table(version.read_parquet(BASIS_FILE), doc["share"],
                                   doc["available"])
    return LatentSetup(latent_case(case, basis), version, grid, layout, basis.names,
                       tuple(doc["deck_coefficients"]))

