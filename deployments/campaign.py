"""Deploy hmflow's campaign flow or its ensemble flow on a schedule, and the report-only flow, to
a process work pool.

The deployments load their flow from this repository checkout (``flow.from_source`` with a
local directory: the deployment's pull step is ``set_working_directory: <repo root>``), so no
Docker image and no remote code storage are needed; a ``prefect worker start --pool POOL`` on a
machine with this checkout and its virtualenv runs them, each flow run in a subprocess of the
worker. The artifact store path and a case file path in the parameters are made absolute here,
so the worker's working directory does not matter.

``hmflow-campaign/NAME`` (``flows/campaign.py:campaign_flow``) calibrates a case's scalar
parameters with a method; ``hmflow-ensemble/NAME`` (``flows/ensemble.py:ensemble_flow``) matches
a case's ``kind = "field"`` parameters by ES-MDA (size, weights and seed from the case's
``[ensemble]`` section); ``hmflow-report/NAME-report`` (``flows/report.py:report_flow``) rebuilds
either one's report from the store (it reads which kind the stored name is bound to).

Python::

    from deployments.campaign import (campaign_parameters, deploy_campaign, deploy_ensemble,
                                      deploy_report, ensemble_parameters, ensure_work_pool)

    ensure_work_pool("hmflow-process")
    params = campaign_parameters(case="synthetic", agent="lm", budget=200, storage="/data/hm")
    deploy_campaign("nightly", cron="0 2 * * *", timezone="UTC", parameters=params)
    deploy_report("nightly-report", storage=params["storage"], campaign=params["campaign"])

    fields = ensemble_parameters(case="fields/case.toml", workers=4, storage="/data/hm")
    deploy_ensemble("weekly-esmda", cron="0 3 * * 6", parameters=fields)
    deploy_report("weekly-esmda-report", storage=fields["storage"], campaign=fields["campaign"])

Command line (creates the pool if missing, then deploys the campaign and its report; an
ensemble is deployed by ``hmflow deploy``, which chooses the flow from the case)::

    python -m deployments.campaign --case synthetic --budget 200 --storage /data/hm
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any
from uuid import UUID

from hmcore.calibration.methods import DEFAULT_AGENT, METHODS
from hmcore.cases import BUILTIN_CASES, case_name

REPO_ROOT = Path(__file__).resolve().parents[1]
CAMPAIGN_ENTRYPOINT = "flows/campaign.py:campaign_flow"
ENSEMBLE_ENTRYPOINT = "flows/ensemble.py:ensemble_flow"
REPORT_ENTRYPOINT = "flows/report.py:report_flow"
CAMPAIGN_FLOW_NAME = "hmflow-campaign"
ENSEMBLE_FLOW_NAME = "hmflow-ensemble"
REPORT_FLOW_NAME = "hmflow-report"
DEFAULT_POOL = "hmflow-process"
DEFAULT_NAME = "nightly"
DEFAULT_CRON = "0 2 * * *"
DEFAULT_STORAGE = "./hmflow-storage"


def ensure_work_pool(name: str = DEFAULT_POOL):
    """Return the work pool ``name``, creating it as a ``process`` pool (with the process
    worker's default job template) when it does not exist. An existing pool of another type is
    refused, since the deployments here need a worker that runs flows in local processes."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import WorkPoolCreate
    from prefect.exceptions import ObjectAlreadyExists, ObjectNotFound
    from prefect.workers.process import ProcessWorker

    with get_client(sync_client=True) as client:
        try:
            pool = client.read_work_pool(name)
        except ObjectNotFound:
            try:
                pool = client.create_work_pool(WorkPoolCreate(
                    name=name, type=ProcessWorker.type,
                    base_job_template=ProcessWorker.get_default_base_job_template(),
                    description="hmflow: campaign, ensemble and report flows in local "
                                "subprocesses"))
            except ObjectAlreadyExists:  # created concurrently
                pool = client.read_work_pool(name)
    if pool.type != ProcessWorker.type:
        raise ValueError(f"work pool {name!r} exists with type {pool.type!r}; hmflow deploys to a "
                         f"'process' pool: choose another --pool name")
    return pool


def campaign_parameters(case: str = "synthetic", agent: str = DEFAULT_AGENT, budget: int = 200,
                        workers: int = 2, seed: int = 0, storage: str | Path = DEFAULT_STORAGE,
                        campaign: str | None = None,
                        agent_settings: dict | None = None, task_runner: str = "threads",
                        dask_address: str | None = None) -> dict[str, Any]:
    """Parameters of ``campaign_flow`` for a deployment: case file and storage made absolute
    (the worker runs the flow in another working directory) and the campaign name fixed, so
    that every scheduled run resumes the same campaign and the report deployment can name it."""
    from hmcore.calibration.registry import default_campaign_name

    params = _absolute_paths({
        "case": str(case), "agent": agent, "budget": int(budget), "workers": int(workers),
        "seed": int(seed), "storage": storage,
        "campaign": campaign or default_campaign_name(case_name(case), agent, int(seed))})
    if agent_settings:
        params["agent_settings"] = dict(agent_settings)
    return {**params, **_runner_parameters(task_runner, dask_address)}


def ensemble_parameters(case: str | Path, workers: int = 2,
                        storage: str | Path = DEFAULT_STORAGE, campaign: str | None = None,
                        task_runner: str = "threads",
                        dask_address: str | None = None) -> dict[str, Any]:
    """Parameters of ``ensemble_flow`` for a deployment: case file and storage made absolute
    and the run's name fixed (default CASE-ensemble, as ``hmflow ensemble`` names it), so that
    every scheduled run resumes the same ensemble run and the report deployment can name it.
    The ensemble's size, weights and seed are the case's ``[ensemble]`` section."""
    # flows.ensemble imports Prefect: only when an ensemble is deployed (as Prefect below)
    from flows.ensemble import default_ensemble_name

    params = _absolute_paths({
        "case": str(case), "workers": int(workers), "storage": storage,
        "campaign": campaign or default_ensemble_name(case_name(case))})
    return {**params, **_runner_parameters(task_runner, dask_address)}


def _runner_parameters(task_runner: str, dask_address: str | None) -> dict[str, Any]:
    """Where the simulator calls run (docs/cluster.md), given only when not the default."""
    if task_runner == "threads" and not dask_address:
        return {}
    return {"task_runner": task_runner, **({"dask_address": dask_address} if dask_address
                                           else {})}


def _absolute_paths(parameters: dict[str, Any]) -> dict[str, Any]:
    """``storage`` and a case file path made absolute (the worker has another working dir)."""
    parameters = dict(parameters)
    parameters["storage"] = str(Path(parameters.get("storage") or DEFAULT_STORAGE)
                                .expanduser().resolve())
    case = parameters.get("case")
    if case is not None and str(case) not in BUILTIN_CASES:
        parameters["case"] = str(Path(case).expanduser().resolve())
    return parameters


def _apply(deployment, work_pool: str) -> UUID:
    """Register ``deployment`` (a RunnerDeployment from ``flow.to_deployment``) on ``work_pool``.

    This is what ``Flow.deploy`` does for a flow from local source, minus its console output and
    its listing of the pool's online workers (with fastapi 0.151 or later beside prefect 3.8.8
    that listing is refused with HTTP 422 - the client sends ``"limit": null`` - which made
    ``Flow.deploy`` fail before anything was deployed; fastapi is now pinned below 0.151)."""
    ensure_work_pool(work_pool)
    return deployment.apply(work_pool_name=work_pool)


def report_deployment_name(name: str) -> str:
    """The report-only deployment of campaign deployment ``name``: its own name in the UI."""
    return f"{name}-report"


def list_deployments() -> list[dict[str, Any]]:
    """hmflow's deployments on the configured server: flow/name, schedules, pool, parameters."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowFilter, FlowFilterName

    out = []
    with get_client(sync_client=True) as client:
        flows = {f.id: f.name for f in client.read_flows(
            flow_filter=FlowFilter(name=FlowFilterName(any_=[
                CAMPAIGN_FLOW_NAME, ENSEMBLE_FLOW_NAME, REPORT_FLOW_NAME])), limit=50)}
        if not flows:
            return out
        for dep in client.read_deployments(flow_filter=FlowFilter(
                name=FlowFilterName(any_=list(flows.values()))), limit=200):
            when = [getattr(s.schedule, "cron", None) or
                    f"every {int(s.schedule.interval.total_seconds())} s"
                    for s in (dep.schedules or []) if s.schedule is not None]
            out.append({"deployment": f"{flows.get(dep.flow_id, '?')}/{dep.name}",
                        "schedule": ", ".join(when) or "none", "pool": dep.work_pool_name,
                        "paused": bool(dep.paused), "parameters": dict(dep.parameters)})
    return sorted(out, key=lambda d: d["deployment"])


def deploy_campaign(name: str = DEFAULT_NAME, cron: str | None = DEFAULT_CRON,
                    timezone: str = "UTC", parameters: dict[str, Any] | None = None,
                    work_pool: str = DEFAULT_POOL, paused: bool = False,
                    concurrency_limit: int | None = 1,
                    tags: list[str] | None = None, interval_s: float | None = None) -> UUID:
    """Deploy ``flows/campaign.py:campaign_flow`` from this checkout as
    ``hmflow-campaign/<name>`` on ``work_pool``, run on ``cron`` in ``timezone`` or every
    ``interval_s`` seconds (no schedule when both are None); return the deployment id.
    Redeploying the same name updates it.

    ``parameters`` are the flow's parameters (see :func:`campaign_parameters`); ``storage`` and
    a case file path are made absolute. ``concurrency_limit`` (default 1) is the deployment's
    Prefect concurrency limit, so that two runs do not work on the same campaign at once."""
    params = _absolute_paths(parameters or campaign_parameters())
    return _deploy(
        CAMPAIGN_ENTRYPOINT, name, work_pool, params, tags=tags,
        schedules=_schedules(cron, timezone, interval_s), paused=paused,
        concurrency_limit=concurrency_limit, description=(
        f"hmflow campaign {params.get('campaign')}: case {params.get('case')}, agent "
        f"{params.get('agent')}, budget {params.get('budget')}, storage {params['storage']}. "
        f"A rerun with the same parameters resumes the campaign (journaled simulator calls "
        f"are not repeated)."))


def deploy_ensemble(name: str, parameters: dict[str, Any], cron: str | None = DEFAULT_CRON,
                    timezone: str = "UTC", work_pool: str = DEFAULT_POOL, paused: bool = False,
                    concurrency_limit: int | None = 1, tags: list[str] | None = None,
                    interval_s: float | None = None) -> UUID:
    """Deploy ``flows/ensemble.py:ensemble_flow`` from this checkout as
    ``hmflow-ensemble/<name>``: as :func:`deploy_campaign` (schedule, concurrency limit 1,
    absolute paths), with the ensemble flow's ``parameters`` (see
    :func:`ensemble_parameters`: a case with field parameters); return the deployment id."""
    params = _absolute_paths(parameters)
    return _deploy(
        ENSEMBLE_ENTRYPOINT, name, work_pool, params, tags=tags or ["hmflow", "ensemble"],
        schedules=_schedules(cron, timezone, interval_s), paused=paused,
        concurrency_limit=concurrency_limit, description=(
        f"hmflow ensemble {params.get('campaign')}: ES-MDA on the field parameters of case "
        f"{params['case']} (its [ensemble] section), storage {params['storage']}. A rerun with "
        f"the same parameters resumes the run (journaled member runs are not repeated)."))


def deploy_report(name: str = DEFAULT_NAME, storage: str | Path = DEFAULT_STORAGE,
                  campaign: str | None = None, work_pool: str = DEFAULT_POOL,
                  tags: list[str] | None = None) -> UUID:
    """Deploy ``flows/report.py:report_flow`` (no schedule) as ``hmflow-report/<name>``: it
    rebuilds a campaign's or an ensemble run's report from stored artifacts, with zero
    simulator calls (named :func:`report_deployment_name` of the campaign's or ensemble's
    deployment by the CLIs). ``storage`` and ``campaign`` are its default parameters
    (changeable per run from the UI/CLI)."""
    params = _absolute_paths({"storage": storage, **({"campaign": campaign} if campaign
                                                    else {})})
    return _deploy(REPORT_ENTRYPOINT, name, work_pool, params, tags=tags, description=(
        "Rebuild an hmflow campaign's or ensemble run's report (Markdown + tables, also "
        "published as Prefect artifacts) from the artifact store; runs no simulation."))


def _schedules(cron: str | None, timezone: str, interval_s: float | None) -> list | None:
    """A cron in ``timezone`` or an interval of ``interval_s`` seconds; None for neither."""
    from datetime import timedelta

    from prefect.schedules import Cron, Interval

    if cron and interval_s:
        raise ValueError("give a cron or an interval, not both")
    return ([Cron(cron, timezone=timezone)] if cron else
            [Interval(timedelta(seconds=interval_s))] if interval_s else None)


def _deploy(entrypoint: str, name: str, work_pool: str, parameters: dict[str, Any], *,
            description: str, tags: list[str] | None = None, schedules: list | None = None,
            paused: bool | None = None, concurrency_limit: int | None = None) -> UUID:
    """The flow at ``entrypoint`` of this checkout as deployment ``name`` on ``work_pool``."""
    from prefect import Flow

    flow = Flow.from_source(source=str(REPO_ROOT), entrypoint=entrypoint)
    deployment = flow.to_deployment(
        name=name, work_pool_name=work_pool, schedules=schedules, parameters=parameters,
        paused=paused, concurrency_limit=concurrency_limit, tags=tags or ["hmflow"],
        description=description)
    return _apply(deployment, work_pool)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m deployments.campaign",
        description="Create the process work pool if missing, deploy the scheduled campaign "
                    "(hmflow-campaign/NAME) and the report-only flow (hmflow-report/NAME-report). "
                    "Uses the Prefect API of the current profile (PREFECT_API_URL).")
    p.add_argument("--name", default=DEFAULT_NAME, help="deployment name (default %(default)s)")
    p.add_argument("--pool", default=DEFAULT_POOL, help="process work pool (default %(default)s)")
    p.add_argument("--cron", default=DEFAULT_CRON, help="cron schedule (default '%(default)s')")
    p.add_argument("--timezone", default="UTC", help="IANA timezone of the cron (default %(default)s)")
    p.add_argument("--no-schedule", action="store_true", help="deploy without a schedule")
    p.add_argument("--case", default="synthetic", help="case TOML or 'synthetic' (default %(default)s)")
    p.add_argument("--agent", default=DEFAULT_AGENT, choices=list(METHODS))
    p.add_argument("--budget", type=int, default=200, help="simulator calls (default %(default)s)")
    p.add_argument("--workers", type=int, default=2, help="simulations at once (default %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--storage", default=DEFAULT_STORAGE,
                   help="artifact store; made absolute (default %(default)s)")
    p.add_argument("--campaign", default=None, help="campaign name (default CASE-AGENT-seedS)")
    p.add_argument("--no-report", action="store_true", help="skip the report-only deployment")
    args = p.parse_args(argv)

    from prefect.settings import PREFECT_API_URL

    if not PREFECT_API_URL.value():
        print("error: no Prefect server configured (PREFECT_API_URL is not set); deployments "
              "on a temporary server would vanish with it. Start one with `prefect server "
              "start` and run `prefect config set PREFECT_API_URL=http://127.0.0.1:4200/api`",
              file=sys.stderr)
        return 2
    try:
        params = campaign_parameters(case=args.case, agent=args.agent, budget=args.budget,
                                     workers=args.workers, seed=args.seed, storage=args.storage,
                                     campaign=args.campaign)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    pool = ensure_work_pool(args.pool)
    print(f"work pool {pool.name!r} (type {pool.type})")
    cron = None if args.no_schedule else args.cron
    dep_id = deploy_campaign(args.name, cron=cron, timezone=args.timezone, parameters=params,
                             work_pool=args.pool)
    when = f"cron '{cron}' ({args.timezone})" if cron else "no schedule"
    print(f"deployment '{CAMPAIGN_FLOW_NAME}/{args.name}' {dep_id}: {when}, parameters {params}")
    if not args.no_report:
        rep_name = report_deployment_name(args.name)
        rep_id = deploy_report(rep_name, storage=params["storage"], campaign=params["campaign"],
                               work_pool=args.pool)
        print(f"deployment '{REPORT_FLOW_NAME}/{rep_name}' {rep_id}: no schedule, parameters "
              f"storage={params['storage']}, campaign={params['campaign']}")
    print(f"next: prefect worker start --pool {args.pool}\n"
          f"      prefect deployment run '{CAMPAIGN_FLOW_NAME}/{args.name}'")
    return 0


if __name__ == "__main__":
    sys.exit(main())
