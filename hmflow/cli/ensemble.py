"""``hmflow ensemble``: ES-MDA on a case's field parameters as a Prefect flow
(:mod:`flows.ensemble`), with a progress bar of the member runs and, at the end, the forecast
of the prior and the posterior and one summary line."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Optional

import typer
from rich.progress import BarColumn, TextColumn, TimeElapsedColumn

from flows.inputs import ensemble_problems
from hmflow.cli.common import (
    DASK_HELP,
    DEFAULT_STORAGE,
    RUNNER_HELP,
    VERBOSE_HELP,
    app,
    checked_campaign,
    console,
    fail,
    folder,
    load_case,
    print_forecast,
    refuse,
)
from hmflow.cli.flowrun import (
    CLUSTER_HELP,
    batch_runner,
    check_cluster,
    check_inputs,
    fit_workers,
    hold_name,
    one_line_failures,
    quiet_storage_faults,
    start_api,
)
from hmflow.console import Watch, prefect_environment


@app.command()
def ensemble(case: str = typer.Option(..., "--case", help="Case TOML file with kind = "
                                      "\"field\" parameters (and an ensemble section)"),
             campaign: Optional[str] = typer.Option(None, "--campaign",
                                                    callback=checked_campaign,
                                                    help="Name in the store (default "
                                                    "CASE-ensemble; the same name resumes)"),
             workers: int = typer.Option(2, "--workers", min=1, help="Member runs at once"),
             storage: Path = typer.Option(DEFAULT_STORAGE, "--storage", help="Artifact store"),
             task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
             dask_address: Optional[str] = typer.Option(None, "--dask-address",
                                                        help=DASK_HELP),
             cluster: Optional[str] = typer.Option(None, "--cluster", help=CLUSTER_HELP),
             verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Match the case's field parameters with ES-MDA (prior, updates, posterior) and print
    the forecast of the prior and the posterior."""
    prefect_environment(verbose)
    task_runner = batch_runner(cluster, task_runner, dask_address)
    # storage imports pandas: keeps `hmflow --help` fast
    from storage import refuse_links

    storage = folder("--storage", storage)
    c = load_case(case)  # every problem before Prefect starts or anything runs
    check_cluster(c, task_runner, storage.resolve())
    refuse(ensemble_problems(c))
    workers = fit_workers(workers, c.simulator.cores_per_run, task_runner)
    check_inputs(workers=workers, task_runner=task_runner)
    start_api()
    # Prefect: only after start_api (it reads its settings on import)
    from flows.ensemble import default_ensemble_name, ensemble_flow

    name = campaign or default_ensemble_name(c.name)
    storage = storage.resolve()
    try:
        refuse_links(storage, name)
    except ValueError as exc:
        fail(str(exc))
    hold_name(storage, name, "ensemble")
    quiet_storage_faults(storage)  # said in one line below, not as a traceback
    spec = c.ensemble
    rounds = len(spec.alphas) + 1
    console.print(f"ensemble [bold]{name}[/]: case {c.name}, {spec.size} members, weights "
                  f"{list(spec.weights)}, {len(c.fields)} field(s), workers {workers}, "
                  f"storage {storage}")
    columns = [TextColumn("[bold]member runs"), BarColumn(), TextColumn(
        "{task.completed}/{task.total}"), TextColumn("ensemble {task.fields[round]}"),
        TimeElapsedColumn()]
    with one_line_failures(storage):
        with Watch(console, member_poll(storage, name, rounds, spec.size), columns,
                   total=spec.size * rounds, initial={"round": "-"}):
            result = ensemble_flow(case=str(case), workers=workers, storage=str(storage),
                                   campaign=name, task_runner=task_runner,
                                   dask_address=dask_address)
    print_forecast(storage, name)
    print_spread(Path(result["report_html"]).with_name("report.json"))
    console.print(result["summary"], highlight=False, soft_wrap=True)
    console.print(f"report: {result['report_html']}", highlight=False, soft_wrap=True)


def print_spread(report_json: Path) -> None:
    """Each field's spread kept by the posterior (and, with a truth, collapsed or not)."""
    for f in json.loads(report_json.read_text()).get("fields", []):
        kept = "n/a" if f["kept"] is None else f"{f['kept']:.0%}"
        console.print(f"field {f['field']}: the posterior keeps {kept} of the prior's spread"
                      + (" [red](collapsed against the truth)[/]" if f["collapsed"] else ""),
                      highlight=False)


def member_poll(storage: Path, campaign: str, rounds: int, size: int) -> Callable[[], dict]:
    """Member runs journaled over every round, and the round running."""

    def poll() -> dict:
        # storage imports pandas: polled only once the flow runs
        from storage import ArtifactStore, EvaluationJournal
        from storage.ensemble import member_journal

        store = ArtifactStore(storage)
        counts = [len(EvaluationJournal(store, campaign, member_journal(i)).indices())
                  for i in range(rounds)]
        current = next((i for i, n in enumerate(counts) if n < size), rounds - 1)
        label = "posterior" if current == rounds - 1 else f"{current}"
        return {"completed": sum(counts), "round": label}

    return poll
