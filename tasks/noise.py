"""The noise a campaign's fit assumes, refined during the campaign: one versioned ``noise``
artifact per refinement (``noise/vNNNN/``: ``noise.json``, the weighed rows
``observations.parquet`` and the table ``noise.parquet``); the latest is the noise of the
campaign's final objective (the case artifact holds the noise estimated from the data before
any fit). A resumed campaign refines at the same calls from the same records, so it finds its
versions already stored and writes none."""

from __future__ import annotations

import json
from pathlib import Path

from hmcore.calibration.objective import Objective
from hmcore.scoring.noise_table import noise_summary
from storage import ArtifactStore, ArtifactVersion, code_version, sha256_json
from storage.jsonable import to_jsonable

NOISE_STEP = "noise"


def store_noise(store_root: str, campaign: str, objective: Objective,
                case_ref: dict) -> ArtifactVersion:
    """Store the noise of ``objective`` (a refinement) under ``campaign``; a version with the
    same inputs (the same refinement of the same case by the same code) is reused, whichever
    version it is."""
    store = ArtifactStore(store_root)
    inputs = {"case": case_ref, **objective.describe()}
    digest = sha256_json(to_jsonable(inputs, "inputs"))
    for version in store.versions(campaign, NOISE_STEP):
        if (version.manifest.get("inputs_hash") == digest
                and version.manifest.get("code_version") == code_version()
                and not version.verify()):
            return version
    obs = objective.observations

    def write(directory: Path) -> None:
        obs.rows.to_parquet(directory / "observations.parquet", index=False)
        noise_summary(obs).to_parquet(directory / "noise.parquet", index=False)
        (directory / "noise.json").write_text(json.dumps(to_jsonable(
            {**objective.describe(), "report": obs.noise_report}), indent=2))

    return store.put(campaign, NOISE_STEP, inputs, write, code_version())


def latest_noise(store: ArtifactStore, campaign: str) -> ArtifactVersion | None:
    """The campaign's refined noise (None: never refined, the case artifact's holds)."""
    return store.latest(campaign, NOISE_STEP)
