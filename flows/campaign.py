"""The campaign flow: prepare case (and, for a ``[latent]`` case, the fields' prior modes,
:mod:`tasks.latent`) -> reference runs (truth or deck values, prior centre) ->
the method in the loop (simulate tasks on a task runner) -> consolidate into Parquet ->
archive the best valid case -> curves and forecast -> report (Markdown, JSON, HTML)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from prefect import flow, get_run_logger
from pydantic import Field

from flows.labels import Progress, campaign_run_name, tag_flow_run
from flows.refuse import USER_ERRORS, input_problems, refused, scalar_problems
from flows.runners import Runner
from flows.runners import task_runner as make_runner
from hmcore.calibration.calls import Job, PhysicsPrecheck
from hmcore.calibration.loop import calibrate
from hmcore.calibration.methods import make_proposer
from hmcore.calibration.objective import Objective
from hmcore.calibration.posterior import DEFAULT_DRAWS, MIN_BUDGET
from hmcore.calibration.registry import (
    DEFAULT_AGENT,
    METHODS,
    default_campaign_name,
    method_version,
)
from hmcore.cases import load_case
from hmcore.model.fingerprint import deck_file_hashes
from hmcore.scoring.evaluation import SCORING_VERSION
from storage import ArtifactStore, EvaluationJournal, validate_name
from storage.latent import BASIS_DOC
from storage.lock import NameHeldError, NameKind, NameLock
from tasks.case import prepare_deck, stored_case_differences
from tasks.curves import collect_curves
from tasks.latent import (
    latent_conflict,
    latent_settings,
    prepare_latent,
    reference_runs,
)
from tasks.noise import store_noise
from tasks.posterior import draw_posterior, plan_jacobian
from tasks.reference import reference_name, reference_settings, run_references
from tasks.results import archive_best, consolidate, report
from tasks.simulate import CAMPAIGN, observation_set, simulate, simulate_parameters

DEFAULT_STORAGE = "./hmflow-storage"


def check_campaign_settings(store_root: str, campaign: str, settings: dict) -> None:
    """A campaign name is bound to its settings: a rerun with the same ones resumes (no call is
    simulated twice); different settings under the same name are refused, never mixed."""
    store = ArtifactStore(store_root)
    stored = store.settings(campaign)
    if stored is not None:
        before = {**SETTINGS_BEFORE_THEY_WERE_STORED, **stored}
        files = _changed_files(before.get("deck_files"), settings.get("deck_files"))
        if files:
            raise ValueError(f"campaign '{campaign}' in {store_root} was started on another "
                             f"model: {files}; resuming would mix two models. Restore the "
                             "file(s), or start a new campaign on the changed model with "
                             f"--campaign {campaign} --fork NEW (it records where it comes "
                             "from; this campaign is left as it is)")
        diff = {k: (before.get(k), v) for k, v in settings.items()
                if k in before and k not in ("deck_files", "case_artifact")
                and before[k] != v}
        case_changes = _case_changes(store_root, before.get("case_artifact"),
                                     settings.get("case_artifact"))
        if case_changes is None:
            bound = before["case_artifact"]
            raise ValueError(
                f"campaign '{campaign}' in {store_root} is bound to a case that is not in the "
                f"store (version {bound.get('version')} of {bound.get('campaign')}/"
                f"{bound.get('step')}), so the case cannot be compared with it. Copy that "
                "folder into the store (archives of benchmarks/export_bench.py carry it), or "
                "choose another name")
        if case_changes:
            raise ValueError(f"campaign '{campaign}' in {store_root} was started on another "
                             f"case: {'; '.join(case_changes)}. Set the stored values in the "
                             "case file to resume it, or choose another --campaign name")
        if diff:
            hint = (f"; or set [misfit] objective = \"{diff['objective'][0]}\" in the case "
                    "file to resume it" if "objective" in diff else "")
            raise ValueError(f"campaign '{campaign}' in {store_root} was started with other "
                             f"settings {diff} (stored, given); choose another --campaign name"
                             + hint)
        return
    store.bind_settings(campaign, settings)


def fork_origin(store_root: str, campaign: str) -> dict:
    """What a fork records of the campaign it comes from: its name and fingerprint (the case
    artifact it was bound to and the hashes of every file its deck read). ValueError when
    there is no such stored campaign."""
    before = ArtifactStore(store_root).settings(validate_name("campaign", campaign))
    if before is None:
        raise ValueError(f"cannot fork from campaign '{campaign}': it is not in {store_root}")
    return {"campaign": campaign, "case_artifact": before.get("case_artifact"),
            "deck_files": before.get("deck_files")}


SETTINGS_BEFORE_THEY_WERE_STORED = {"scoring_version": 1, "method_version": 1,
                                    "objective": "E"}
"""What a campaign.json written before a setting was stored means by its absence: scored by
the first rules. A setting stored neither then nor now (``workers`` in older campaigns) is
not compared."""


def _changed_files(before: dict | None, now: dict | None) -> str:
    """Which deck files differ between the stored and the given hashes ('' when none, or when
    the campaign was started before the files were stored)."""
    if not before or now is None:
        return ""
    changed = [f"{p} changed" for p in sorted(before) if p in now and now[p] != before[p]]
    changed += [f"{p} is no longer read" for p in sorted(set(before) - set(now))]
    changed += [f"{p} is read now" for p in sorted(set(now) - set(before))]
    return "; ".join(changed)


def _case_changes(store_root: str, before: dict | None, given: dict | None) -> list[str] | None:
    """How the given case differs in meaning from the one the campaign was started on (empty:
    the same case; None: the case the campaign is bound to is not in the store). The same
    stored content is the same case; a version written again by newer hmflow code (more
    settings stored, at their defaults) is too, and resumes the campaign."""
    if not isinstance(before, dict) or not isinstance(given, dict):
        return []
    if before.get("content_hash") == given.get("content_hash"):
        return []
    store = ArtifactStore(store_root)
    try:
        stored = store.get(before["campaign"], before["step"], before["version"])
    except (LookupError, KeyError, FileNotFoundError, ValueError):
        return None
    try:
        now = store.get(given["campaign"], given["step"], given["version"])
        return stored_case_differences(stored, now)
    except (LookupError, KeyError, FileNotFoundError, ValueError) as exc:
        return [f"the stored case cannot be compared ({exc})"]


Agent = Literal[METHODS]  # a choice in the UI's run form


@flow(name="hmflow-campaign", log_prints=True, flow_run_name=campaign_run_name)
def campaign_flow(case: str = "synthetic", agent: Agent = DEFAULT_AGENT,
                  budget: Annotated[int, Field(ge=1)] = 200,
                  workers: Annotated[int, Field(ge=1)] = 2, seed: Annotated[int, Field(ge=0)] = 0,
                  storage: str = DEFAULT_STORAGE, campaign: str | None = None,
                  agent_settings: dict | None = None, reference: str | None = None,
                  task_runner: Runner = "threads", dask_address: str | None = None,
                  forked_from: str | None = None,
                  forecast_draws: Annotated[int, Field(ge=0)] | None = None) -> dict:
    """Calibrate ``case`` with ``budget`` simulator calls, ``workers`` at a time.

    Args:
        case: Case TOML file (an absolute path on the worker) or the built-in 'synthetic'.
        agent: Calibration method: lm (hmflow's default: bounded least squares), sac-paper
            (the reference paper's SAC), sac, or another (random, sobol, cmaes, de, bo, esmda).
        budget: Simulator calls in all. A rerun with a larger budget continues a random or
            sobol campaign; methods whose plan depends on the budget (sac's final exploit
            call, cmaes, de, esmda, sac-paper) are refused at the first call that differs.
        workers: Simulations at once.
        seed: Seed of the method.
        storage: Artifact store directory.
        campaign: Campaign name; the same name resumes (default CASE-AGENT-seedS).
        agent_settings: Settings of sac or sac-paper (advanced; see hmcore.calibration.methods).
        reference: Campaign holding the two reference runs (the truth's or the deck's own
            values, and the prior centre), outside the budget; default CAMPAIGN-reference
            (a benchmark shares its own among its campaigns).
        task_runner: Where the simulator calls run: threads (subprocesses of this flow's
            process) or dask (a Dask cluster, see dask_address).
        dask_address: Scheduler of an existing Dask cluster (tcp://host:8786); default the
            DASK_ADDRESS environment variable, else a local cluster of `workers` processes.
        forked_from: A stored campaign this new one starts from (`hmflow run --fork`): its
            name and fingerprint (case artifact, deck file hashes) are recorded in this
            campaign's campaign.json; it is only read, never written.
        forecast_draws: Parameter sets drawn from the Laplace posterior at the best call and
            simulated after the fit, apart from the budget, for the forecast (tasks.posterior);
            default 20 when the budget is at least 50 calls, else 0 (the best-calls spread).
    """
    logger = get_run_logger()
    try:  # bad input from the UI or the API: one clear line, no traceback, no simulation
        problems = input_problems(agent, budget, workers, task_runner)
        if problems:
            raise ValueError("; ".join(problems))
        storage = str(Path(storage).expanduser().resolve())
        loaded = load_case(case)
        problems = scalar_problems(loaded, latent=True)
        if problems:
            raise ValueError("; ".join(problems))
        origin = fork_origin(storage, forked_from) if forked_from else None
    except USER_ERRORS as exc:
        return refused(exc)
    campaign = campaign or default_campaign_name(loaded.name, agent, seed)
    reference = reference or reference_name(campaign)
    tag_flow_run("hmflow", f"case:{loaded.name}", f"agent:{agent}", f"seed:{seed}")
    lock = NameLock(storage, campaign, NameKind.CAMPAIGN)  # a deployment's run, too
    try:
        lock.acquire()
    except NameHeldError as exc:
        return refused(exc)
    try:
        conflict = latent_conflict(storage, campaign, loaded)  # before anything is written
        if conflict:
            return refused(ValueError(conflict))
        latent = prepare_latent(loaded, storage, campaign) if loaded.latent else None
        if latent is not None:  # the fields' modes join the space, first
            loaded = latent.case
            logger.info(f"campaign {campaign}: the fields moved by {len(latent.names)} modes "
                        f"of their prior ({latent.version.read_json(BASIS_DOC)['share']:.1%} "
                        "of its variance)")
        simulator_of = latent.job_simulator if latent is not None else (lambda job: None)
        case_version = prepare_deck(loaded, case, storage, campaign)
        try:  # a name bound to other settings (another case, method or version): one clear line
            check_campaign_settings(storage, campaign, {**latent_settings(loaded, latent),
                "case_artifact": case_version.ref(), "agent": agent, "seed": seed,
                "agent_settings": agent_settings or {}, "workers": workers,
                "scoring_version": SCORING_VERSION, "method_version": method_version(agent),
                "objective": loaded.misfit.objective,
                "reference": reference, "deck_files": deck_file_hashes(loaded),
                **({"forked_from": origin} if origin else {})})
            check_campaign_settings(storage, reference, {**reference_settings(case_version),
                                                         **latent_settings(loaded, latent)})
        except ValueError as exc:
            return refused(exc)
        journal = EvaluationJournal(ArtifactStore(storage), campaign)
        done = {r["index"]: r for r in journal.rows()}
        if done:
            logger.info(f"resuming campaign {campaign}: {len(done)} calls already journaled")
        proposer = make_proposer(agent, loaded.space.dim, seed, workers, budget,
                                 **(agent_settings or {}))
        observations = observation_set(loaded)  # every record keeps its simulated rows
        objective = Objective.of_case(loaded, observations)
        final = [objective]  # the objective as the campaign ends (its noise refined)

        def refined(better: Objective) -> None:
            final[0] = better
            store_noise(storage, campaign, better, case_version.ref())
            logger.info(f"campaign {campaign}: noise refinement {better.refinement} from the "
                        f"residuals of call {better.refined_from + 1}")

        progress = Progress(campaign, budget)
        progress.update([r for i, r in done.items() if i < budget])

        with make_runner(task_runner, workers, dask_address, loaded.cluster) as runner:
            references = run_references(loaded, storage, reference, runner, observations,
                                        **reference_runs(latent))

            def run_jobs(jobs, destination=CAMPAIGN) -> list[dict]:
                futures = [runner.submit(simulate, simulate_parameters(
                    loaded, job, storage, campaign, seed, agent, observations,
                    destination=destination, simulator=simulator_of(job))) for job in jobs]
                return [f.result() for f in futures]

            def evaluate_batch(jobs: list[Job]) -> list[dict]:
                records = run_jobs(jobs)
                progress.update(records)
                return records

            calibrate(proposer, loaded.space, evaluate_batch, budget, workers, done,
                      precheck=PhysicsPrecheck.of(loaded), objective=objective, on_refine=refined)
            results = consolidate(storage, campaign, loaded.space.names, final[0], references)
            best = archive_best(storage, campaign, results)
            draws = (forecast_draws if forecast_draws is not None
                     else DEFAULT_DRAWS if budget >= MIN_BUDGET else 0)
            if draws:
                jacobian = plan_jacobian(loaded, storage, campaign)  # none when lm made one
                if jacobian.jobs:
                    logger.info(f"campaign {campaign}: {len(jacobian.jobs)} finite-difference "
                                f"runs at call {jacobian.best_index + 1} for its posterior, "
                                "apart from the budget")
                run_jobs(jacobian.jobs, jacobian.destination)
                plan = draw_posterior(loaded, storage, campaign, seed, draws)
                logger.info(f"campaign {campaign}: forecast from {len(plan.jobs)} posterior "
                            "draws, simulated apart from the budget" if plan.jobs else
                            f"campaign {campaign}: no posterior draws: {plan.reason}")
                run_jobs(plan.jobs, plan.destination)
        collect_curves(storage, campaign, reference)
        rep = report(storage, campaign)
        summary = rep.read_json("report.json")
        best_doc = summary.get("best")
        logger.info(f"campaign {campaign}: " + (
            f"best by {summary.get('objective', 'E')} at call {best_doc['index'] + 1}: E "
            f"{best_doc['E']:.6g}, likelihood {best_doc.get('likelihood') or float('nan'):.6g}"
            if best_doc else "no valid call"))
        return {"campaign": campaign, "storage": storage, "results": results.ref(),
                "best": best.ref() if best else None, "report": rep.ref(),
                "report_path": str(rep.file("report.md")),
                "report_html": str(rep.file("report.html"))}
    finally:
        lock.release()
