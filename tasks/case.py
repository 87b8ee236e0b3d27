"""Deck preparation: validate the case and store what it was (hashes, settings, parameters)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

import hmcore.model.case as case_models
from hmcore.model.case import Case
from hmcore.model.fingerprint import case_fingerprint
from hmcore.model.parameters import Parameter
from hmcore.model.run_deck import prepare_run_deck
from hmcore.scoring.noise_table import noise_summary
from hmcore.scoring.observations import ObservationSet
from storage import ArtifactStore, ArtifactVersion, code_version, refuse_links
from storage.jsonable import to_jsonable


def fingerprint_differences(version: ArtifactVersion, case: Case) -> list[str]:
    """Which of ``case``'s input hashes (:func:`case_fingerprint`) differ from those a stored
    ``case`` artifact version was made from (empty: the same case)."""
    inputs = version.manifest.get("inputs", {})
    return sorted(k for k, v in case_fingerprint(case).items() if inputs.get(k) != v)


@task(name="prepare-deck", cache_policy=NO_CACHE)
def prepare_deck(case: Case, case_ref: str, store_root: str, campaign: str) -> ArtifactVersion:
    """Store the case as run: neutral per-run deck, case file, history, settings and hashes.

    The latest version is reused when it was made from the same files (whatever path or name
    the case was given by this time) by the same code, so that a campaign stays bound to one
    case artifact (a diagnosis ``--from-campaign`` names the case by its absolute path)."""
    store = ArtifactStore(store_root)
    refuse_links(store.root, campaign)  # never write through a linked campaign folder
    latest = store.latest(campaign, "case")
    if (latest is not None and latest.manifest.get("code_version") == code_version()
            and not fingerprint_differences(latest, case) and not latest.verify()):
        return dataclasses.replace(latest, reused=True)

    def write(directory: Path) -> None:
        prepare_run_deck(case.deck, {}, case.space, directory / "deck", case.info)
        (directory / "case.toml").write_bytes(case.source.read_bytes())
        case.observed.to_parquet(directory / "observed.parquet", index=False)
        observations = ObservationSet.from_case(case)  # the rows the fit weighs, their sigma
        observations.rows.to_parquet(directory / "observations.parquet", index=False)
        noise_summary(observations).to_parquet(directory / "noise.parquet", index=False)
        (directory / "case.json").write_text(json.dumps(to_jsonable({
            "name": case.name, "source": str(case.source), "deck": str(case.deck),
            "observed": str(case.observed_path), "parameters": [p.model_dump() for p in case.space.parameters],
            "time_tolerance_days": case.time_tolerance_days, "history_end_days": case.history_end_days,
            "misfit": case.misfit.model_dump(), "simulator": case.simulator.model_dump(),
            "physics": case.physics.model_dump(), "wells": sorted(case.info.wells),
            "dims": case.info.dims, "end_days": case.info.end_days,
            "fit_history_end_days": observations.history_end_days,
            **({"latent": case.latent.model_dump(mode="json")} if case.latent else {})}),
            indent=2))

    return store.put(campaign, "case", {"case": case_ref, **case_fingerprint(case)}, write,
                     code_version())


ADDED_COLUMNS = {"controlled": False}
"""History columns newer hmflow stores, and what a stored history without them meant."""

_SETTINGS = {"misfit": "MisfitSettings", "simulator": "SimulatorSettings",
             "physics": "PhysicsSettings"}
_COMPARED = ("name", "time_tolerance_days", "history_end_days", "wells", "dims", "end_days")


def _meaning(version: ArtifactVersion) -> dict:
    """A stored case as the current code reads it: settings and parameters with today's
    defaults for what an older version did not store; paths and the case file's bytes
    (comments, layout) left out, the prepared deck by its files' hashes."""
    stored = version.read_json("case.json")
    meaning = {k: stored.get(k) for k in _COMPARED}
    for key, model in _SETTINGS.items():
        cls = getattr(case_models, model)
        for field, value in cls.model_validate(stored.get(key, {}), strict=False
                                               ).model_dump(mode="json").items():
            meaning[f"{key}.{field}"] = value
    for p in stored.get("parameters", []):
        for field, value in Parameter.model_validate(p, strict=False).model_dump(
                mode="json").items():
            meaning[f"parameter {p.get('name')}.{field}"] = value
    meaning["parameter order"] = [p.get("name") for p in stored.get("parameters", [])]
    meaning["files the deck reads"] = (version.manifest.get("inputs") or {}).get("deck_files")
    files = version.manifest.get("files", {})
    meaning["deck files"] = {k: v.get("sha256") for k, v in files.items()
                             if k.startswith("deck/")}
    return meaning


def _history(version: ArtifactVersion):
    observed = version.read_parquet("observed.parquet")
    for column, absent in ADDED_COLUMNS.items():
        if column not in observed:
            observed[column] = absent
    return observed[sorted(observed.columns)].reset_index(drop=True)


def stored_case_differences(before: ArtifactVersion, after: ArtifactVersion) -> list[str]:
    """What differs in meaning between two stored versions of a case (empty: the same case,
    e.g. written again by newer hmflow code that stores more settings, at their defaults).
    Each item names the setting and both values: 'physics.perm_cap_md: 20000.0 (stored),
    None (given)'."""
    old, new = _meaning(before), _meaning(after)
    for k in ("files the deck reads",):  # not stored by the oldest versions: not compared
        if old.get(k) is None or new.get(k) is None:
            old.pop(k, None), new.pop(k, None)
    changes = [f"{k}: {old.get(k)!r} (stored), {new.get(k)!r} (given)"
               for k in sorted(set(old) | set(new))
               if k != "deck files" and old.get(k) != new.get(k)]
    if old["deck files"] != new["deck files"]:
        changes.append("the prepared deck's files differ")
    h0, h1 = _history(before), _history(after)
    if list(h0.columns) != list(h1.columns) or not h0.equals(h1):
        changes.append("the history (observed.parquet) differs")
    return changes
