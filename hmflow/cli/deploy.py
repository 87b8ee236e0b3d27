"""``hmflow deploy``: the campaign (and its report-only rerun) as deployments on a Prefect
server's process work pool, or the list of hmflow's deployments there."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from flows.inputs import input_problems
from hmcore.calibration.registry import DEFAULT_AGENT
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
from hmflow.cli.flowrun import dask_problems


@app.command()
def deploy(name: str = typer.Option("nightly", "--name", help="Deployment name; the report-only "
                                    "deployment is NAME-report"),
           pool: str = typer.Option("hmflow-process", "--pool", help="Process work pool "
                                    "(created when missing)"),
           cron: Optional[str] = typer.Option(None, "--cron", help="Cron schedule (default "
                                              "'0 2 * * *' when no --interval)"),
           interval: Optional[int] = typer.Option(None, "--interval", min=1, help="Run every "
                                                  "N seconds instead of a cron"),
           timezone: str = typer.Option("UTC", "--timezone", help="IANA timezone of the cron"),
           no_schedule: bool = typer.Option(False, "--no-schedule", help="Deploy without a "
                                            "schedule (run it from the UI)"),
           case: str = typer.Option("synthetic", "--case", help=CASE_HELP),
           agent: str = typer.Option(DEFAULT_AGENT, "--agent", help="Calibration method"),
           budget: int = typer.Option(200, "--budget", min=1),
           workers: int = typer.Option(2, "--workers", min=1),
           seed: int = typer.Option(0, "--seed", min=0),
           storage: Path = typer.Option(DEFAULT_STORAGE, "--storage",
                                        help="Artifact store (made absolute)"),
           campaign: Optional[str] = typer.Option(None, "--campaign", callback=checked_campaign, help="Campaign name "
                                                  "(default CASE-AGENT-seedS)"),
           no_report: bool = typer.Option(False, "--no-report", help="Skip the report-only "
                                          "deployment"),
           task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
           dask_address: Optional[str] = typer.Option(None, "--dask-address", help=DASK_HELP),
           list_: bool = typer.Option(False, "--list", help="List hmflow's deployments on the "
                                      "server and exit")) -> None:
    """Deploy the campaign on a schedule (and its report-only rerun) to a Prefect server's
    process work pool; a worker started with `prefect worker start --pool POOL` runs them."""
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
            p = d["parameters"]
            t.add_row(d["deployment"], d["schedule"], str(d["pool"]), str(d["paused"]),
                      str(p.get("campaign", "")), str(p.get("agent", "")),
                      str(p.get("budget", "")))
        console.print(t)
        return
    problems = []
    if cron and interval:
        problems.append("give --cron or --interval, not both")
    if no_schedule and (cron or interval):
        problems.append("--no-schedule takes no --cron or --interval")
    if case != "synthetic" and not Path(case).is_file():
        problems.append(f"--case {case}: no such file (a case TOML or 'synthetic')")
    problems += input_problems(agent, budget, workers, task_runner, spell=option)
    problems += dask_problems(task_runner, dask_address)
    refuse(problems)
    params = dep.campaign_parameters(case=case, agent=agent, budget=budget, workers=workers,
                                     seed=seed, storage=storage, campaign=campaign,
                                     task_runner=task_runner, dask_address=dask_address)
    work_pool = dep.ensure_work_pool(pool)
    cron = None if (no_schedule or interval) else (cron or dep.DEFAULT_CRON)
    dep_id = dep.deploy_campaign(name, cron=cron, timezone=timezone, parameters=params,
                                 work_pool=pool, interval_s=None if no_schedule else interval,
                                 tags=["hmflow", f"case:{dep.case_name(case)}", f"agent:{agent}"])
    when = (f"cron '{cron}' ({timezone})" if cron else f"every {interval} s" if interval and not
            no_schedule else "no schedule")
    console.print(f"work pool {work_pool.name!r} (type {work_pool.type})")
    console.print(f"deployment '{dep.CAMPAIGN_FLOW_NAME}/{name}' {dep_id}: {when}; campaign "
                  f"{params['campaign']}, case {params['case']}, agent {agent}, budget {budget}",
                  highlight=False)
    if not no_report:
        rep_name = dep.report_deployment_name(name)
        rep_id = dep.deploy_report(rep_name, storage=params["storage"],
                                   campaign=params["campaign"], work_pool=pool)
        console.print(f"deployment '{dep.REPORT_FLOW_NAME}/{rep_name}' {rep_id}: no schedule; "
                      f"rebuilds the report of {params['campaign']}", highlight=False)
    console.print(f"next: prefect worker start --pool {pool}", highlight=False)
