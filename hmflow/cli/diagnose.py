"""``hmflow diagnose``: what the calibrated model gets wrong, as a Prefect flow with a progress
display."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from flows.inputs import input_problems, scalar_problems
from hmcore.errors import CaseError
from hmflow.cli.common import (
    CASE_HELP,
    DASK_HELP,
    DEFAULT_STORAGE,
    KINDS_HELP,
    RUNNER_HELP,
    VERBOSE_HELP,
    app,
    checked_campaign,
    console,
    fail,
    load_case,
    option,
    refuse,
)
from hmflow.cli.flowrun import (
    CLUSTER_HELP,
    batch_runner,
    check_cluster,
    dask_problems,
    hold_name,
    one_line_failures,
    progress_columns,
    quiet_storage_faults,
    start_api,
)
from hmflow.console import Watch, diagnosis_poll, prefect_environment


@app.command()
def diagnose(case: Optional[str] = typer.Option(None, "--case", help=CASE_HELP + " Default: "
                                                 "the --from-campaign's case, else 'synthetic'."),
             storage: Path = typer.Option(DEFAULT_STORAGE, "--storage",
                                          help="Artifact store"),
             budget: Optional[int] = typer.Option(None, "--budget", min=1, help="Cap on simulator "
                                                  "calls (default: as many as the steps need)"),
             workers: int = typer.Option(2, "--workers", min=1, help="Simulations at once"),
             campaign: Optional[str] = typer.Option(None, "--campaign", callback=checked_campaign, help="Name the diagnosis "
                                                    "is stored under (default: the "
                                                    "--from-campaign, else CASE-diagnosis)"),
             from_campaign: Optional[str] = typer.Option(
                 None, "--from-campaign", callback=checked_campaign, help="Start from this stored campaign's best "
                 "parameters instead of calibrating the case's parameters first"),
             task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
             dask_address: Optional[str] = typer.Option(None, "--dask-address",
                                                        help=DASK_HELP),
             kinds: Optional[str] = typer.Option(None, "--kinds", help=KINDS_HELP),
             cluster: Optional[str] = typer.Option(None, "--cluster", help=CLUSTER_HELP),
             verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Find what the calibrated model gets wrong, name the cause, extend the model, measure the
    gain on the fitted and the held-back history; writes diagnosis.json (path printed)."""
    prefect_environment(verbose)
    task_runner = batch_runner(cluster, task_runner, dask_address)
    # the diagnosis and storage import pandas: keeps `hmflow --help` fast
    from hmcore.diagnosis.settings import parse_kinds
    from storage import ArtifactStore

    problems, kind_list = input_problems(task_runner=task_runner, spell=option), None
    if kinds is not None:
        try:
            kind_list = parse_kinds(kinds, "--kinds")
        except ValueError as exc:
            problems += str(exc).split("; ")
    refuse(problems + dask_problems(task_runner, dask_address))
    if case:
        check_budget(load_case(case), budget, kind_list, from_campaign is not None)
    start_api()
    # Prefect: only after start_api (it reads its settings on import)
    from flows.diagnose import campaign_start, default_campaign_name, diagnose_flow, print_diagnosis

    calibrated = None
    if from_campaign:
        try:
            case, calibrated = campaign_start(ArtifactStore(storage.resolve()), from_campaign,
                                              case)
        except (LookupError, ValueError, CaseError) as exc:
            fail(str(exc))
        campaign = campaign or from_campaign  # the diagnosis goes into that campaign's report
    case = case or "synthetic"
    c = load_case(case)  # clear errors before any simulator time or Prefect start-up
    check_cluster(c, task_runner, storage.resolve())
    check_budget(c, budget, kind_list, calibrated is not None)
    storage = storage.resolve()
    hold_name(storage, campaign or default_campaign_name(c.name), "diagnosis")
    quiet_storage_faults(storage)  # said in one line below, not as a traceback
    # what flows.diagnose.diagnose_command does, with a progress display until the flow ends
    poll = diagnosis_poll(storage, campaign or default_campaign_name(c.name))
    with one_line_failures(storage):
        with Watch(console, poll, progress_columns("diagnose" if budget else "diagnose-open"),
                   total=budget, initial={"step": "-"}):
            result = diagnose_flow(case=str(case), storage=str(storage), budget=budget,
                                   campaign=campaign, workers=workers, calibrated=calibrated,
                                   task_runner=task_runner, dask_address=dask_address,
                                   kinds=list(kind_list) if kind_list else None)
    print_diagnosis(result, console)


def check_budget(case, budget: Optional[int], kinds: Optional[tuple[str, ...]],
                 given: bool) -> None:
    """Exit 2 with one line when the case has no scalar parameter to calibrate, or when
    ``--budget`` cannot cover the diagnosis's minimum (see
    :func:`hmcore.diagnosis.workflow.minimum_runs`), before any simulator time."""
    refuse(scalar_problems(case))
    if budget is None:
        return
    # the diagnosis imports pandas: keeps `hmflow --help` fast
    from hmcore.diagnosis.settings import DiagnosisSettings
    from hmcore.diagnosis.workflow import budget_problem

    settings = DiagnosisSettings(budget=budget, **({"kinds": kinds} if kinds else {}))
    problem = budget_problem(case, settings, given, "--budget")
    if problem:
        fail(problem, soft_wrap=True)
