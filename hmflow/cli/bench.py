"""``hmflow bench``: the equal-budget benchmark of the calibration methods as a Prefect flow."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from flows.inputs import input_problems, scalar_problems
from hmcore.calibration.registry import ABLATIONS, AGENTS, METHODS
from hmflow.cli.common import (
    CASE_HELP,
    DASK_HELP,
    DEFAULT_STORAGE,
    RUNNER_HELP,
    VERBOSE_HELP,
    app,
    console,
    fail,
    folder,
    load_case,
    option,
    refuse,
)
from hmflow.cli.flowrun import (
    CLUSTER_HELP,
    batch_runner,
    check_cluster,
    fit_workers,
    hold_name,
    one_line_failures,
    progress_columns,
    quiet_storage_faults,
    start_api,
)
from hmflow.console import Watch, bench_poll, prefect_environment


@app.command()
def bench(case: str = typer.Option("synthetic", "--case", help=CASE_HELP),
          methods: str = typer.Option("all", "--methods", help="Comma-separated methods, or "
                                      "'all': " + ", ".join(AGENTS) + "; ablations: "
                                      + ", ".join(ABLATIONS)),
          seeds: int = typer.Option(5, "--seeds", min=1, help="Seeds 0 .. K-1 for every method"),
          budget: int = typer.Option(100, "--budget", min=1, help="Simulator calls per method "
                                     "and seed (every run counts: Jacobian runs, ensemble "
                                     "members)"),
          workers: int = typer.Option(2, "--workers", min=1, help="Simulations at once"),
          storage: Path = typer.Option(DEFAULT_STORAGE, "--storage"),
          name: Optional[str] = typer.Option(None, "--name", help="Benchmark name (default "
                                             "bench-CASE); the same name resumes"),
          task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
          dask_address: Optional[str] = typer.Option(None, "--dask-address",
                                                     help=DASK_HELP),
          cluster: Optional[str] = typer.Option(None, "--cluster", help=CLUSTER_HELP),
          verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Equal-budget benchmark: every method x seed is an ordinary campaign (a stopped benchmark
    resumes where it was), then one table, Parquet files and a best-so-far plot."""
    prefect_environment(verbose)
    task_runner = batch_runner(cluster, task_runner, dask_address)
    storage = folder("--storage", storage)
    c = load_case(case)
    check_cluster(c, task_runner, storage.resolve())
    refuse(scalar_problems(c, latent=True))
    workers = fit_workers(workers, c.simulator.cores_per_run, task_runner)
    chosen = list(AGENTS) if methods == "all" else [m.strip() for m in methods.split(",")
                                                    if m.strip()]
    unknown = [m for m in chosen if m not in METHODS]
    if unknown or not chosen:
        fail(f"--methods: unknown {unknown or 'none given'}; choose from {list(METHODS)}")
    refuse([p for m in chosen for p in input_problems(m, budget, workers, spell=option)]
           + input_problems(task_runner=task_runner, spell=option))
    storage = storage.resolve()
    hold_name(storage, name or f"bench-{c.name}", "benchmark")  # (flows.bench.bench_names' rule)
    start_api()
    # Prefect: only after start_api (it reads its settings on import)
    from flows.bench import bench_flow, bench_names

    console.print(f"benchmark on case {c.name}: {len(chosen)} methods x {seeds} seeds x {budget} "
                  f"calls, {workers} workers, storage {storage}")
    quiet_storage_faults(storage)  # said in one line below, not as a traceback
    bench_name, _, campaigns = bench_names(c.name, chosen, list(range(seeds)), name)
    with one_line_failures(storage):
        with Watch(console, bench_poll(storage, campaigns, budget, workers, bench_name),
                   progress_columns("bench"),
                   total=len(campaigns) * budget, initial={"current": "starting"}):
            result = bench_flow(case=str(case), methods=chosen, seeds=list(range(seeds)),
                                budget=budget, workers=workers, storage=str(storage), name=name,
                                task_runner=task_runner, dask_address=dask_address)
    console.print(Path(result["summary_path"]).read_text(), highlight=False, soft_wrap=True)
    console.print(f"table: {result['summary_path']}\nplot:  {result['plot_path']}")
