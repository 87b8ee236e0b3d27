"""The ensemble flow (issue 41): history matching of a case's field parameters by ES-MDA.

load and check the case (refused before any simulation) -> store the case -> the prior
(drawn, or the user's GRDECL files; stored once) -> for each inflation factor: the members'
runs (one journaled simulator task per member, ``workers`` at once) -> the update (the next
ensemble stored) -> after the last update the posterior's runs -> the forecast (P90/P50/P90 of
the prior and the posterior).

Every member's run is journaled when it ends, so a run killed anywhere and started again with
the same command simulates only the members not yet journaled; the ensembles are stored
versions, and an update repeats exactly (its perturbations are seeded by the iteration).
Members that fail are left out of the update while ``min_realizations`` remain; below that
the run stops with one line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from prefect import flow, get_run_logger
from prefect.states import Failed
from pydantic import Field

from flows.campaign import DEFAULT_STORAGE, check_campaign_settings
from flows.inputs import ensemble_problems
from flows.labels import Progress, named_run, tag_flow_run
from flows.refuse import USER_ERRORS, input_problems, refused
from flows.runners import Runner
from flows.runners import task_runner as make_runner
from hmcore.cases import load_case
from hmcore.model.fingerprint import deck_file_hashes
from storage import ArtifactStore
from storage.lock import NameHeldError, NameKind, NameLock
from tasks.case import prepare_deck
from tasks.ensemble import (
    ensemble_settings,
    forecast_step,
    member_jobs,
    member_records,
    prepare_ensemble,
    prior_step,
    submit_members,
    update_step,
)
from tasks.ensemble_report import ensemble_report


def default_ensemble_name(case_name: str) -> str:
    return f"{case_name}-ensemble"


@flow(name="hmflow-ensemble", log_prints=True,
      flow_run_name=named_run("campaign", "ensemble"))
def ensemble_flow(case: str = "synthetic", workers: Annotated[int, Field(ge=1)] = 2,
                  storage: str = DEFAULT_STORAGE, campaign: str | None = None,
                  task_runner: Runner = "threads", dask_address: str | None = None) -> dict:
    """Match ``case``'s field parameters with ES-MDA (its ``[ensemble]`` section: size,
    weights, min_realizations, localisation, seed), ``workers`` member runs at a time.

    Args:
        case: Case TOML file with ``kind = "field"`` parameters (an absolute path on the
            worker).
        workers: Member runs at once.
        storage: Artifact store directory.
        campaign: Name of the run in the store (default CASE-ensemble); the same name resumes.
        task_runner: Where the runs go: threads (subprocesses of this flow's process) or dask.
        dask_address: Scheduler of an existing Dask cluster (default DASK_ADDRESS, else a
            local cluster of `workers` processes).
    """
    logger = get_run_logger()
    try:  # bad input from the command line, the UI or the API: one line, no simulation
        problems = input_problems(workers=workers, task_runner=task_runner)
        storage = str(Path(storage).expanduser().resolve())
        loaded = load_case(case)
        problems += ensemble_problems(loaded)
        if problems:
            raise ValueError("; ".join(problems))
        campaign = campaign or default_ensemble_name(loaded.name)
        stored = ArtifactStore(storage).settings(campaign)
        if stored is not None and stored.get("kind") != "ensemble":
            raise ValueError(f"'{campaign}' in {storage} is a calibration campaign, not an "
                             "ensemble run; choose another --campaign name")
    except USER_ERRORS as exc:
        return refused(exc)
    tag_flow_run("hmflow", "ensemble", f"case:{loaded.name}")
    lock = NameLock(storage, campaign, NameKind.ENSEMBLE)  # a deployment's run, too
    try:
        lock.acquire()
    except NameHeldError as exc:
        return refused(exc)
    try:
        case_version = prepare_deck(loaded, case, storage, campaign)
        try:  # a name bound to another case or ensemble: one clear line
            check_campaign_settings(storage, campaign, ensemble_settings(
                loaded, case_version, deck_file_hashes(loaded)))
        except ValueError as exc:
            return refused(exc)
        setup = prepare_ensemble(loaded)
        ensemble = prior_step(loaded, setup, storage, campaign, case_version)
        iterations = len(loaded.ensemble.alphas)
        progress = Progress(campaign, loaded.ensemble.size * (iterations + 1))
        planned: dict[int, list[int]] = {}
        with make_runner(task_runner, workers, dask_address, loaded.cluster) as runner:
            for i in range(iterations + 1):  # the last round runs the posterior
                jobs = member_jobs(loaded, ensemble, i, setup.layout)
                planned[i] = [j.index for j in jobs]
                done = member_records(storage, campaign, i)
                if done:
                    logger.info(f"{campaign} ensemble {i}: {len(done)} of {len(jobs)} members "
                                "already journaled")
                progress.update(list(done.values()))
                futures = submit_members(runner, loaded, setup, ensemble, i, jobs, storage,
                                         campaign)
                for f in futures:
                    progress.update([f.result()])
                if i == iterations:
                    break
                ensemble = update_step(loaded, setup, ensemble,
                                       member_records(storage, campaign, i), i, storage,
                                       campaign)
                if isinstance(ensemble, str):  # too few members ran: the reason, in one line
                    return stopped(ensemble)
        forecast = forecast_step(loaded, setup.observations, storage, campaign, iterations,
                                 planned)
        report = ensemble_report(storage, campaign)
        doc = forecast.read_json("summary.json")
        line = (f"ensemble {campaign}: {loaded.ensemble.size} members, {iterations} "
                f"assimilation(s), {doc['runs']} runs ({doc['failed']} failed); "
                f"{doc['headline'] or 'no forecast (no member ran to the end)'}")
        logger.info(line)
        return {"campaign": campaign, "storage": storage, "posterior": ensemble.ref(),
                "forecast": forecast.ref(), "runs": doc["runs"], "failed": doc["failed"],
                "report": report.ref(), "report_html": str(report.file("report.html")),
                "summary": line}
    finally:
        lock.release()


def stopped(message: str):
    """Log why the iterations stopped (one line) and return the Failed state the flow ends
    in; the members' records and the ensembles stored so far stay in the store."""
    text = " ".join(message.split())
    get_run_logger().error(text)
    return Failed(message=text)
