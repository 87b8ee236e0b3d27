"""The campaign flow: prepare case -> SAC in the loop (simulate tasks on a task runner) ->
consolidate into Parquet -> archive the best valid case -> report."""

from __future__ import annotations

import json
from pathlib import Path

from prefect import flow, get_run_logger

from hmcore.agents import make_proposer
from hmcore.calibration import Job, calibrate
from storage import ArtifactStore, EvaluationJournal
from tasks.case import prepare_deck, validate_case
from tasks.results import archive_best, consolidate, report
from tasks.simulate import observation_set, simulate

DEFAULT_STORAGE = "./hmflow-storage"


def default_campaign_name(case_name: str, agent: str, seed: int) -> str:
    return f"{case_name}-{agent}-seed{seed}"


def check_campaign_settings(store_root: str, campaign: str, settings: dict) -> None:
    """A campaign name is bound to its settings: a rerun with the same ones resumes (no call is
    simulated twice); different settings under the same name are refused, never mixed."""
    path = Path(store_root) / campaign / "campaign.json"
    if path.exists():
        before = json.loads(path.read_text())
        diff = {k: (before.get(k), v) for k, v in settings.items()
                if _comparable(k, before.get(k)) != _comparable(k, v)}
        if diff:
            raise ValueError(f"campaign '{campaign}' in {store_root} was started with other "
                             f"settings {diff} (stored, given); choose another --campaign name")
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(settings, indent=2))
    tmp.replace(path)


def _comparable(key: str, value):
    """The case is the same case when its stored content is: a new version of the same content
    (written by newer hmflow code) resumes the campaign; other content never does."""
    if key == "case_artifact" and isinstance(value, dict):
        return value.get("content_hash")
    return value


@flow(name="hmflow-campaign", log_prints=True)
def campaign_flow(case: str = "synthetic", agent: str = "sac", budget: int = 200, workers: int = 2,
                  seed: int = 0, storage: str = DEFAULT_STORAGE, campaign: str | None = None,
                  agent_settings: dict | None = None) -> dict:
    """Calibrate ``case`` with ``budget`` simulator calls, ``workers`` at a time."""
    logger = get_run_logger()
    storage = str(Path(storage).resolve())
    loaded = validate_case(case)
    campaign = campaign or default_campaign_name(loaded.name, agent, seed)
    case_version = prepare_deck(loaded, case, storage, campaign)
    check_campaign_settings(storage, campaign, {
        "case_artifact": case_version.ref(), "agent": agent, "seed": seed,
        "agent_settings": agent_settings or {}})
    journal = EvaluationJournal(ArtifactStore(storage), campaign)
    done = {r["index"]: r for r in journal.rows()}
    if done:
        logger.info(f"resuming campaign {campaign}: {len(done)} calls already journaled")
    proposer = make_proposer(agent, loaded.space.dim, seed, workers, budget,
                             **(agent_settings or {}))
    observations = (observation_set(loaded) if getattr(proposer, "needs_residuals", False)
                    else None)

    def evaluate_batch(jobs: list[Job]) -> list[dict]:
        futures = [simulate.submit(loaded, job, storage, campaign, seed, agent, observations)
                   for job in jobs]
        return [f.result() for f in futures]

    calibrate(proposer, loaded.space, evaluate_batch, budget, workers, done)
    results = consolidate(storage, campaign, loaded.space.names)
    best = archive_best(storage, campaign, results)
    rep = report(storage, campaign)
    summary = rep.read_json("report.json")
    logger.info(f"campaign {campaign}: best {summary.get('best')}")
    return {"campaign": campaign, "storage": storage, "results": results.ref(),
            "best": best.ref() if best else None, "report": rep.ref(),
            "report_path": str(rep.file("report.md"))}
