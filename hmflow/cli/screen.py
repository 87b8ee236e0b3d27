"""``hmflow screen``: which parameters move which responses (sensitivity screening as a
Prefect flow, :mod:`flows.screen`), its ranked table, tornado charts and a new case file with
the parameters that matter switched on."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from hmflow.cli.common import (
    CASE_HELP,
    DASK_HELP,
    DEFAULT_STORAGE,
    RUNNER_HELP,
    VERBOSE_HELP,
    app,
    checked_campaign,
    console,
    folder,
    load_case,
    refuse,
)
from hmflow.cli.flowrun import (
    check_inputs,
    fit_workers,
    hold_name,
    one_line_failures,
    progress_columns,
    quiet_storage_faults,
    start_api,
)
from hmflow.console import Watch, campaign_poll, prefect_environment


@app.command()
def screen(case: str = typer.Option("synthetic", "--case", help=CASE_HELP),
           method: str = typer.Option("morris", "--method", help="oat (each parameter to its "
                                      "bounds from the prior centre: 2d+1 calls), morris "
                                      "(SALib's elementary effects; default), sobol (SALib's "
                                      "Sobol' indices: N(d+2) calls)"),
           budget: Optional[int] = typer.Option(None, "--budget", help="Simulator calls "
                                                "(default: oat 2d+1, morris 10(d+1), sobol "
                                                "64(d+2))"),
           workers: int = typer.Option(2, "--workers", min=1, help="Simulations at once"),
           seed: int = typer.Option(0, "--seed", min=0),
           storage: Path = typer.Option(DEFAULT_STORAGE, "--storage", help="Artifact store"),
           campaign: Optional[str] = typer.Option(None, "--campaign", callback=checked_campaign,
                                                  help="Screening name; the same name resumes "
                                                  "(default CASE-screen-METHOD-seedS)"),
           task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
           dask_address: Optional[str] = typer.Option(None, "--dask-address", help=DASK_HELP),
           centre: str = typer.Option("prior", "--centre", help="Where oat starts: prior (the "
                                      "middle of each parameter's box, log-aware) or deck (the "
                                      "deck's own values, clipped into the box)"),
           verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Screen the case's parameters: rank them per well response and on the misfit, draw a
    tornado per response, and write a new case file with those that matter switched on."""
    prefect_environment(verbose)
    # SALib and the design: only when the command runs (keeps `hmflow --help` fast)
    from hmcore.calibration.sensitivity import (
        ScreenMethod,
        default_budget,
        default_screen_name,
        screen_problems,
    )

    storage = folder("--storage", storage).resolve()
    c = load_case(case)
    refuse(screen_problems(str(c.source), c.space.dim, method, budget, centre))
    workers = fit_workers(workers, c.simulator.cores_per_run, task_runner)
    check_inputs(None, None, workers, task_runner)
    calls = budget or default_budget(ScreenMethod(method), c.space.dim)
    name = campaign or default_screen_name(c.name, method, seed)
    hold_name(storage, name, "campaign")
    start_api()
    # Prefect: only after start_api (it reads its settings on import)
    from flows.screen import screen_flow

    console.print(f"screening [bold]{name}[/]: case {c.name}, method {method}, "
                  f"{c.space.dim} parameters, budget {calls}, workers {workers}, seed {seed}",
                  highlight=False)
    console.print(f"storage: {escape(str(storage))}", soft_wrap=True, highlight=False)
    quiet_storage_faults(storage)  # said in one line below, not as a traceback
    with one_line_failures(storage):
        try:
            with Watch(console, campaign_poll(storage, name, calls), progress_columns("run"),
                       total=calls, initial={"best": "-"}):
                result = screen_flow(case=str(case), method=method, budget=budget,
                                     workers=workers, seed=seed, storage=str(storage),
                                     screen=name, task_runner=task_runner,
                                     dask_address=dask_address, centre=centre)
        except KeyboardInterrupt:
            console.print(f"screening [bold]{name}[/] stopped; the same command resumes it")
            raise
    print_result(result)


def print_result(result: dict) -> None:
    """The design, the rule and the parameters it switched on, where the new case file and
    the report are."""
    design = result["design"]
    extra = (f", {design['trajectories']} trajectories on {design['levels']} levels"
             if design.get("trajectories") else "")
    extra += f", Sobol' N = {design['base_n']}" if design.get("base_n") else ""
    console.print(f"\n[bold]{result['screening']}[/]: {result['method']}, {design['calls']} "
                  f"calls, seed {design['seed']}{extra}; {result['failed_calls']} failed",
                  highlight=False)
    console.print(f"rule: a parameter matters when its {result['rule']}", highlight=False)
    console.print(f"switched on: {', '.join(result['chosen']) or 'none'}; screened out: "
                  f"{', '.join(result['dropped']) or 'none'}", highlight=False)
    said = "new case file" if result.get("new_file") else "case file (written before)"
    console.print(f"{said}: {escape(result['case_file'])}", soft_wrap=True, highlight=False)
    if Path(result["case_file"]).name != Path(result["case_source"]).stem + ".screened.toml":
        console.print("  (the first free name: an existing file is never overwritten)")
    console.print(f"report: {escape(result['report_html'])}", soft_wrap=True, highlight=False)
