"""``hmflow deploy``: the case's flow - the calibration campaign, or the ensemble for a case of
field parameters - and its report-only rerun as deployments on a Prefect server's process work
pool, or the list of hmflow's deployments there."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, cast

import typer
from rich.table import Table

from flows.inputs import ensemble_problems, input_problems, scalar_problems
from hmcore.calibration.registry import DEFAULT_AGENT
from hmcore.errors import CaseError
from hmcore.model.case import BUILTIN_CASES
from hmflow.cli.common import (
    CASE_HELP,
    DASK_HELP,
    DEFAULT_STORAGE,
    RUNNER_HELP,
    app,
    checked_campaign,
    console,
    fail,
    option,
    refuse,
)
from hmflow.cli.flowrun import CLUSTER_HELP, batch_runner, check_cluster, dask_problems

if TYPE_CHECKING:  # the case module imports pandas: keeps `hmflow --help` fast
    from hmcore.model.case import Case

FlowKind = Literal["campaign", "ensemble"]
FLOWS: tuple[FlowKind, ...] = ("campaign", "ensemble")
DEFAULT_BUDGET = 200
CAMPAIGN_ONLY = ("--agent", "--budget", "--seed")
"""Options of a calibration campaign that an ensemble has no use for (its size, weights and
seed are the case's [ensemble] section)."""


@dataclass(frozen=True)
class Target:
    """What ``hmflow deploy`` deploys for a case: the flow, why it was chosen, the case (None
    when it was not loaded: the built-in case, a missing or invalid file) and every problem
    of the case for that flow."""

    flow: FlowKind
    why: str
    case: Case | None = None
    problems: tuple[str, ...] = ()


def deploy_target(case: str, flow: str | None) -> Target:
    """The flow to deploy for ``case``: ``--flow`` when given, else chosen from the case - the
    ensemble when its parameters include kind = "field" (``hmflow run`` refuses a case of
    fields only), the campaign otherwise; with the flow's own rules of the case
    (:func:`flows.inputs.ensemble_problems`, :func:`flows.inputs.scalar_problems`)."""
    if flow is not None and flow not in FLOWS:
        problem = (f"--flow must be one of {list(FLOWS)}, got {flow!r} (or leave it out: the "
                   "flow is chosen from the case)")
        return Target("campaign", "", problems=(problem,))
    given = f"--flow {flow}"
    if case in BUILTIN_CASES and flow != "ensemble":  # scalar parameters; not generated here
        return Target("campaign", given if flow else f"the built-in case '{case}'")
    if case not in BUILTIN_CASES and not Path(case).is_file():
        return Target(flow or "campaign", given,
                      problems=(f"--case {case}: no such file (a case TOML or 'synthetic')",))
    # hmcore.cases imports pandas: keeps `hmflow --help` fast
    from hmcore.cases import load_case

    try:
        loaded = load_case(case)
    except CaseError as exc:
        return Target(flow or "campaign", given,
                      problems=tuple(f"--case {case}: {p}" for p in exc.problems))
    names = ", ".join(f.name for f in loaded.fields)
    chosen = cast(FlowKind, flow or ("ensemble" if loaded.fields and loaded.latent is None
                                     else "campaign"))
    why = given if flow else (f"case {loaded.name} has a [latent] section (its fields moved "
                              "by their prior's modes)" if loaded.latent is not None
                              else f"case {loaded.name} has field parameters {names}"
                              if loaded.fields else f"case {loaded.name} has no field parameter")
    problems = (ensemble_problems(loaded) if chosen == "ensemble"
                else scalar_problems(loaded, latent=True))  # a campaign moves [latent] modes
    return Target(chosen, why, loaded, tuple(problems))


def campaign_only_problems(target: Target, given: list[str]) -> list[str]:
    """``--agent``/``--budget``/``--seed`` given for an ensemble: one line naming them."""
    if target.flow != "ensemble" or not given:
        return []
    one = len(given) == 1
    scalars = target.case is not None and target.case.space.parameters
    return [f"{', '.join(given)} {'does' if one else 'do'} not apply to an ensemble deployment "
            f"({target.why} -> the ensemble flow; its size, weights and seed are the case's "
            f"[ensemble] section): remove {'it' if one else 'them'}" +
            (", or give --flow campaign to calibrate the case's scalar parameters with a "
             "method" if scalars else "")]


@app.command()
def deploy(name: str = typer.Option("nightly", "--name", help="Deployment name; the report-only "
                                    "deployment is NAME-report"),
           pool: str = typer.Option("hmflow-process", "--pool", help="Process work pool "
                                    "(created when missing)"),
           cron: str | None = typer.Option(None, "--cron", help="Cron schedule (default "
                                              "'0 2 * * *' when no --interval)"),
           interval: int | None = typer.Option(None, "--interval", min=1, help="Run every "
                                                  "N seconds instead of a cron"),
           timezone: str = typer.Option("UTC", "--timezone", help="IANA timezone of the cron"),
           no_schedule: bool = typer.Option(False, "--no-schedule", help="Deploy without a "
                                            "schedule (run it from the UI)"),
           case: str = typer.Option("synthetic", "--case", help=CASE_HELP),
           flow: str | None = typer.Option(None, "--flow", help="campaign or ensemble "
                                              "(default: chosen from the case: the ensemble "
                                              "when its parameters include kind = \"field\", "
                                              "else the campaign)"),
           agent: str | None = typer.Option(None, "--agent", help="Calibration method "
                                               f"(default {DEFAULT_AGENT}; a campaign only)"),
           budget: int | None = typer.Option(None, "--budget", min=1, help="Simulator calls "
                                                f"(default {DEFAULT_BUDGET}; a campaign only)"),
           workers: int = typer.Option(2, "--workers", min=1, help="Simulations (an "
                                       "ensemble's member runs) at once"),
           seed: int | None = typer.Option(None, "--seed", min=0, help="The method's seed "
                                              "(default 0; a campaign only)"),
           storage: Path = typer.Option(DEFAULT_STORAGE, "--storage",
                                        help="Artifact store (made absolute)"),
           campaign: str | None = typer.Option(None, "--campaign", callback=checked_campaign,
                                                  help="Campaign name (default CASE-AGENT-seedS; "
                                                  "an ensemble: CASE-ensemble)"),
           no_report: bool = typer.Option(False, "--no-report", help="Skip the report-only "
                                          "deployment"),
           task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
           dask_address: str | None = typer.Option(None, "--dask-address", help=DASK_HELP),
           cluster: str | None = typer.Option(None, "--cluster", help=CLUSTER_HELP),
           list_: bool = typer.Option(False, "--list", help="List hmflow's deployments on the "
                                      "server and exit")) -> None:
    """Deploy the case's flow on a schedule (and its report-only rerun) to a Prefect server's
    process work pool; a worker started with `prefect worker start --pool POOL` runs them.

    The flow is chosen from the case: a case whose parameters include kind = "field" deploys
    the ensemble (hmflow-ensemble/NAME, as `hmflow ensemble`: ES-MDA with the size, weights
    and seed of the case's ensemble section), any other case the calibration campaign
    (hmflow-campaign/NAME, as `hmflow run`); --flow campaign|ensemble chooses for a case of
    both kinds. --agent, --budget and --seed are the campaign's: given for an ensemble, they
    are refused (nothing is deployed)."""
    # Prefect and the deployments: only when a command deploys (keeps `hmflow --help` fast)
    from prefect.settings import PREFECT_API_URL

    from deployments import campaign as dep

    if not PREFECT_API_URL.value():
        fail("no Prefect server configured (PREFECT_API_URL is not set): deployments on a "
             "temporary server would vanish with it. Start one with `prefect server start`, "
             "then `prefect config set PREFECT_API_URL=http://127.0.0.1:4200/api`")
    if list_:
        t = Table(title=f"hmflow deployments on {PREFECT_API_URL.value()}")
        for col in ("deployment", "schedule", "pool", "paused", "campaign", "agent", "budget"):
            t.add_column(col)
        for d in dep.list_deployments():
            p = d["parameters"]  # an ensemble or a report has no agent nor budget: '-'
            t.add_row(d["deployment"], d["schedule"], str(d["pool"]), str(d["paused"]),
                      str(p.get("campaign", "")), str(p.get("agent", "-")),
                      str(p.get("budget", "-")))
        console.print(t)
        return
    task_runner = batch_runner(cluster, task_runner, dask_address)
    problems = []
    if cron and interval:
        problems.append("give --cron or --interval, not both")
    if no_schedule and (cron or interval):
        problems.append("--no-schedule takes no --cron or --interval")
    target = deploy_target(case, flow)
    problems += target.problems
    if target.flow == "ensemble":
        problems += campaign_only_problems(target, [o for o, v in zip(
            CAMPAIGN_ONLY, (agent, budget, seed)) if v is not None])
        problems += input_problems(workers=workers, task_runner=task_runner, spell=option)
    else:
        agent, budget = agent or DEFAULT_AGENT, budget or DEFAULT_BUDGET
        seed = 0 if seed is None else seed
        problems += input_problems(agent, budget, workers, task_runner, spell=option)
    problems += dask_problems(task_runner, dask_address)
    refuse(problems)
    if target.case is not None:
        check_cluster(target.case, task_runner, storage.resolve())
    tags = ["hmflow", f"case:{dep.case_name(case)}"]
    if target.flow == "ensemble":
        params = dep.ensemble_parameters(case=case, workers=workers, storage=storage,
                                         campaign=campaign, task_runner=task_runner,
                                         dask_address=dask_address)
        deploy_flow, flow_name, tags = dep.deploy_ensemble, dep.ENSEMBLE_FLOW_NAME, tags + [
            "ensemble"]
        spec = target.case.ensemble
        what = (f"ensemble {params['campaign']} ({target.why}), case {params['case']}, "
                f"{spec.size} members, weights {list(spec.weights)}")
    else:
        params = dep.campaign_parameters(case=case, agent=agent, budget=budget,
                                         workers=workers, seed=seed, storage=storage,
                                         campaign=campaign, task_runner=task_runner,
                                         dask_address=dask_address)
        deploy_flow, flow_name, tags = dep.deploy_campaign, dep.CAMPAIGN_FLOW_NAME, tags + [
            f"agent:{agent}"]
        what = (f"campaign {params['campaign']}, case {params['case']}, agent {agent}, "
                f"budget {budget}")
    work_pool = dep.ensure_work_pool(pool)
    cron = None if (no_schedule or interval) else (cron or dep.DEFAULT_CRON)
    dep_id = deploy_flow(name, parameters=params, cron=cron, timezone=timezone, work_pool=pool,
                         interval_s=None if no_schedule else interval, tags=tags)
    when = (f"cron '{cron}' ({timezone})" if cron else f"every {interval} s" if interval and not
            no_schedule else "no schedule")
    console.print(f"work pool {work_pool.name!r} (type {work_pool.type})")
    console.print(f"deployment '{flow_name}/{name}' {dep_id}: {when}; {what}", highlight=False)
    if not no_report:
        rep_name = dep.report_deployment_name(name)
        rep_id = dep.deploy_report(rep_name, storage=params["storage"],
                                   campaign=params["campaign"], work_pool=pool)
        console.print(f"deployment '{dep.REPORT_FLOW_NAME}/{rep_name}' {rep_id}: no schedule; "
                      f"rebuilds the report of {params['campaign']}", highlight=False)
    console.print(f"next: prefect worker start --pool {pool}", highlight=False)
