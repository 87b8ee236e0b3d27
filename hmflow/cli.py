"""The ``hmflow`` command line: check, evaluate, run, report, diagnose, hide, reveal.

``check`` and ``evaluate`` use hmcore alone; ``run``, ``report`` and ``diagnose`` start the
Prefect flows in ``flows/`` (an ephemeral Prefect server is used when none is configured).
"""

from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from hmcore.calibration.methods import ABLATIONS, AGENTS, DEFAULT_AGENT, METHODS
from hmcore.errors import CaseError
from hmcore.units import deck_unit
from hmflow.console import (Watch, bench_poll, campaign_poll, diagnosis_poll, prefect_environment,
                            status_text, summary_table)

# before Prefect is imported (every command imports it lazily): no usage telemetry (no ERROR
# about it on a machine without internet), Prefect's own log lines in the terminal from WARNING
# up (``--verbose``: all); a user's own settings win - see hmflow.console.prefect_environment
prefect_environment()

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Batch history matching of reservoir models with OPM Flow.")
console = Console()
err_console = Console(stderr=True)

CASE_HELP = "Case TOML file, or the built-in name 'synthetic' (generated on first use)."
VERBOSE_HELP = ("Also show Prefect's own log lines (INFO: temporary server, flow and task runs); "
                "without it only its warnings and errors")

RUNNER_HELP = ("Where the simulator calls run: threads (subprocesses of this process) or dask "
               "(a Dask cluster: --dask-address, DASK_ADDRESS, else a local one of --workers "
               "processes); see docs/cluster.md")
DASK_HELP = "Dask scheduler address, e.g. tcp://head-node:8786 (default: DASK_ADDRESS)"



def _checked_campaign(value: Optional[str]) -> Optional[str]:
    """A campaign name given on the command line: refused at once (exit 2, the rule stated)
    when it is empty or could leave the store (``''``, ``../S``, ``a/b``)."""
    if value is None:
        return value
    from storage import validate_name

    try:
        return validate_name("campaign", value)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None


@app.callback()
def _signals() -> None:
    """SIGTERM (``kill PID``, a batch system's time limit) stops hmflow as Ctrl-C does: the
    flow run ends as cancelled, the temporary Prefect server is stopped, and the journal keeps
    every finished call (the same command resumes). Without this, SIGTERM ended the process
    at once and left the temporary server running."""
    import signal

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, interrupt)


def _folder(option: str, path: Path) -> Path:
    """A folder option (``--out``, ``--storage``): exit 2 with one line when it names a file
    or cannot be a path, before anything runs."""
    try:
        path = path.expanduser()
    except RuntimeError as exc:  # ~nosuchuser
        err_console.print(f"[red]x[/] {option} {path}: {exc}", highlight=False)
        raise typer.Exit(2)
    if path.exists() and not path.is_dir():
        err_console.print(f"[red]x[/] {option} {path} is a file, not a folder; give a folder "
                          "(it is created when missing)", highlight=False)
        raise typer.Exit(2)
    if any(p.exists() and not p.is_dir() for p in path.parents):
        err_console.print(f"[red]x[/] {option} {path}: a part of the path is a file, not a "
                          "folder", highlight=False)
        raise typer.Exit(2)
    return path


def _load(case: str):
    from hmcore.cases import load_case

    try:
        return load_case(case)
    except CaseError as exc:
        print_problems(f"Case {case} is not valid", exc.problems)
        raise typer.Exit(2)


def print_problems(title: str, problems) -> None:
    """Every problem on stderr: where, what, fix (the user's text printed as it is, never read
    as rich markup: '[[parameters]]' stays)."""
    from rich.markup import escape

    err_console.print(f"[bold red]{escape(title)}[/] - {len(problems)} problem(s):")
    for p in problems:
        err_console.print(f"  [red]x[/] {escape(p.where)}\n      {escape(p.what)}"
                          + (f"\n      fix: {escape(p.fix)}" if p.fix else ""), highlight=False)


def _num(v, digits=4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}f}"


def print_tables(metrics: dict, title: str = "") -> None:
    """Print the paper's three tables (categories; C_match per well; GOR / water cut per well),
    in the paper's rounding."""
    from hmcore.reporting.paper_tables import cell, paper_tables

    heads = {"categories": "match by category", "wells": "C_match (%) per well and category",
             "ratios": "GOR and water cut per well (records used, left out and why)"}
    for key, df in paper_tables(metrics).items():
        t = Table(title=f"{title} {heads[key]}".strip())
        for col in df.columns:
            t.add_column(str(col), justify="left" if col in ("category", "ratio", "well", "why")
                         else "right")
        for row in df.itertuples(index=False):
            t.add_row(*[cell(c, v) for c, v in zip(df.columns, row)])
        console.print(t)


def parse_sets(sets: list[str], names: list[str]) -> dict[str, float]:
    values = {}
    problems = []
    for item in sets:
        name, sep, val = item.partition("=")
        if not sep:
            problems.append(f"--set {item!r}: expected NAME=VALUE")
            continue
        if name not in names:
            import difflib

            near = difflib.get_close_matches(name, names, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            problems.append(f"--set {item!r}: unknown parameter {name!r}{hint}; known: {names}")
            continue
        try:
            value = float(val)
        except ValueError:
            problems.append(f"--set {item!r}: {val!r} is not a number")
            continue
        if not math.isfinite(value):
            problems.append(f"--set {item!r}: {val!r} is not a finite number (give a value "
                            "inside the parameter's bounds)")
            continue
        values[name] = value
    if problems:
        for p in problems:
            err_console.print(f"[red]x[/] {p}")
        raise typer.Exit(2)
    return values


@app.command()
def init(deck: Path = typer.Option(..., "--deck", help="The field's deck (.DATA)"),
         out: Optional[Path] = typer.Option(None, "--out", help="Case file to write (default: "
                                            "<deck name>.toml here); never overwritten"),
         summary: Optional[Path] = typer.Option(None, "--summary", help="Take the measured data "
                                                "from this summary file (.SMSPEC, or an .RSM "
                                                "text summary) instead of the deck's "
                                                "WCONHIST/WCONINJH records"),
         observed: Optional[Path] = typer.Option(None, "--observed", help="Use this observed CSV "
                                                 "(well, days, quantity, value[, units]) as it is"),
         name: Optional[str] = typer.Option(None, "--name", help="Case name (default: from the "
                                            "deck's file name)")) -> None:
    """Write a starting case for a deck: observed data from its history, default parameters."""
    from hmcore.model.case_init import starting_case, write_starting_case

    if summary is not None and observed is not None:
        err_console.print("[red]x[/] give --summary or --observed, not both")
        raise typer.Exit(2)
    case_name_ = name or re.sub(r"[^A-Za-z0-9_.-]+", "_", deck.stem.lower())
    out = out or Path(f"{case_name_}.toml")
    try:
        start = starting_case(deck, case_name_, observed, summary)
        case_path, observed_path = write_starting_case(start, out, observed)
    except CaseError as exc:
        print_problems(f"Cannot start a case from {deck}", exc.problems)
        raise typer.Exit(2)
    except FileExistsError as exc:
        err_console.print(f"[red]x[/] {exc}")
        raise typer.Exit(2)
    kinds = start.wells_by_kind()
    console.print(f"wrote [bold]{case_path}[/] ({len(start.parameters)} parameters on, "
                  f"{len(start.optional)} more commented out)")
    if observed is None:
        counts = start.observed.groupby("quantity").size().to_dict()
        console.print(f"wrote [bold]{observed_path}[/]: {len(start.observed)} rows {counts} "
                      f"from {start.source}, in {start.info.unit_system} units")
    console.print(f"  wells: {len(kinds['producer'])} producer(s), {len(kinds['injector'])} "
                  f"injector(s); faults: {len(start.info.faults)}")
    for why in start.skipped:
        console.print(f"  [yellow]not used[/]: {why}", highlight=False)
    console.print(f"next: hmflow check --case {case_path}")


@app.command()
def check(case: str = typer.Option("synthetic", "--case", help=CASE_HELP)) -> None:
    """Validate the case (deck, history, parameters); runs no simulation."""
    c = _load(case)
    obs = c.observed
    console.print(f"[green]OK[/] case [bold]{c.name}[/] ({c.source})")
    console.print(f"  deck      {c.deck}: grid {'x'.join(map(str, c.info.dims))}, "
                  f"{c.info.nactive} active cells, wells {sorted(c.info.wells)}, "
                  f"schedule {c.info.end_days:g} days")
    derived = obs[obs.derived].groupby("quantity").size().to_dict()
    measured = obs[~obs.derived].groupby("quantity").size().to_dict()
    console.print(f"  history   {c.observed_path}: {int((~obs.derived).sum())} measured rows "
                  f"{measured}" + (f", derived {derived}" if derived else ""))
    console.print(f"  fitting   days <= {c.history_end_days if c.history_end_days else 'end'}, "
                  f"tolerance {c.time_tolerance_days:g} d, misfit {c.misfit.variant}")
    console.print(f"  units     {c.info.unit_system}: " + ", ".join(
        f"{q} {deck_unit(q, c.info.unit_system)}" for q in sorted(set(obs.quantity))))
    if "controlled" in obs and obs.controlled.any():
        fixed = obs[obs.controlled].groupby("quantity").size().to_dict()
        used = sorted(set(c.informative.quantity))
        console.print(f"  control   history-mode wells fix {fixed} row(s) by their control "
                      f"(WCONHIST/WCONINJH CMODE): left out of E, which uses {used}")
    for warning in c.info.warnings:
        console.print(f"  [yellow]warning[/] OPM Flow tolerates this and runs on: {warning}",
                      highlight=False)
    if c.info.history.skipped:
        console.print(f"  [yellow]note[/] {len(c.info.history.skipped)} history record(s) not "
                      "used: " + "; ".join(c.info.history.skipped[:5]))
    for p in c.space.parameters:
        console.print(f"  parameter {p.name:<12} {p.kind:<9} [{p.low:g}, {p.high:g}] {p.description}")


@app.command()
def evaluate(case: str = typer.Option("synthetic", "--case", help=CASE_HELP),
             set_: list[str] = typer.Option([], "--set", help="NAME=VALUE (repeatable); "
                                             "unset parameters keep the deck's values"),
             out: Path = typer.Option(..., "--out", help="Output directory (must not exist or be empty)"),
             simulator: Optional[str] = typer.Option(None, "--simulator", help="'opm' or a command "
                                                     "template like 'flow {deck} --output-dir={run_dir}'")) -> None:
    """Run one simulation and score it: writes OUT/metrics.json and OUT/responses.parquet."""
    from hmcore.scoring.evaluation import evaluate as run_one
    from hmcore.scoring.evaluation import simulator_for
    from hmcore.reporting.report import metrics_document
    from hmcore.simulation.simulator import make_simulator

    c = _load(case)
    if simulator:
        from hmcore.model.validation import simulator_problems

        bad = simulator_problems(simulator, "--simulator")
        if bad:
            print_problems(f"--simulator {simulator!r} cannot run", bad)
            raise typer.Exit(2)
    values = parse_sets(set_, c.space.names)
    bounds = c.space.check_in_bounds(values)
    if bounds:
        console.print(f"[yellow]note[/]: {'; '.join(bounds)} (evaluated anyway)")
    out = _folder("--out", out)
    if out.exists() and any(out.iterdir()):
        err_console.print(f"[red]x[/] {out} exists and is not empty; hmflow never overwrites results "
                          "(choose a new --out)")
        raise typer.Exit(2)
    out.mkdir(parents=True, exist_ok=True)
    sim = (make_simulator(simulator, c.simulator.timeout_s, c.simulator.threads,
                          processes=c.simulator.processes) if simulator
           else simulator_for(c))
    ev = run_one(c, values, out / "run", sim)
    doc = metrics_document(ev)
    (out / "metrics.json").write_text(json.dumps(doc, indent=2))
    if ev.responses is not None:
        ev.responses.to_parquet(out / "responses.parquet", index=False)
    console.print(f"status [bold]{ev.status.value}[/]  E = {_num(ev.E, 6)}  penalty = {_num(ev.penalty)}  "
                  f"reward = {_num(ev.reward, 6)}  coverage = {_num(ev.coverage, 3)}  "
                  f"simulator {ev.sim_time_s:.1f} s")
    if ev.reason:
        console.print(f"reason: {ev.reason}")
    if ev.metrics:
        print_tables(ev.metrics)
    written = [out / "metrics.json"] + ([out / "responses.parquet"] if ev.responses is not None else [])
    console.print("wrote " + " and ".join(map(str, written)))
    if ev.status.value == "FAIL":
        raise typer.Exit(1)


def _columns(kind: str) -> list:
    """The progress bar's columns: ``run`` (calls of the budget, best E), ``bench`` (calls of
    methods x seeds x budget, the method and seed running), ``diagnose`` (simulations of the
    budget) and ``diagnose-open`` (no budget: a spinner with the count)."""
    from rich.progress import (BarColumn, SpinnerColumn, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    count = TextColumn("{task.completed}/{task.total}")
    if kind == "run":
        return [TextColumn("[bold]calls"), BarColumn(), count,
                TextColumn("best E {task.fields[best]}"), TimeElapsedColumn(), TextColumn("ETA"),
                TimeRemainingColumn()]
    if kind == "bench":
        return [TextColumn("[bold]calls"), BarColumn(), count, TimeElapsedColumn(),
                TextColumn("ETA"), TimeRemainingColumn(), TextColumn("{task.fields[current]}")]
    if kind == "diagnose":  # the steps may stop short of the budget
        return [TextColumn("[bold]simulations (budget {task.total})"), BarColumn(), count,
                TimeElapsedColumn(), TextColumn("step {task.fields[step]}")]
    return [SpinnerColumn(), TextColumn("[bold]simulations {task.completed}"),
            TimeElapsedColumn(), TextColumn("step {task.fields[step]}")]


@app.command()
def run(case: str = typer.Option("synthetic", "--case", help=CASE_HELP),
        agent: str = typer.Option(DEFAULT_AGENT, "--agent", help="lm (the default: least "
                                  "squares on the whitened residuals, the benchmark's winner), "
                                  "sac (hmflow's SAC), sac-paper (the reference paper's SAC "
                                  "exactly: SB3 learn(), budget a multiple of --workers), "
                                  "random, sobol, cmaes, de, bo, esmda"),
        budget: int = typer.Option(200, "--budget", min=1, help="Simulator calls"),
        workers: int = typer.Option(2, "--workers", min=1, help="Simulations at once"),
        seed: int = typer.Option(0, "--seed"),
        storage: Path = typer.Option(Path("./hmflow-storage"), "--storage", help="Artifact store"),
        campaign: Optional[str] = typer.Option(None, "--campaign", callback=_checked_campaign, help="Campaign name "
                                               "(default CASE-AGENT-seedS; the same name resumes)"),
        task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
        dask_address: Optional[str] = typer.Option(None, "--dask-address", help=DASK_HELP),
        fork: Optional[str] = typer.Option(None, "--fork", callback=_checked_campaign,
                                           help="Start a new campaign FORK on the case as it "
                                           "is now, recording that it comes from --campaign "
                                           "(which is left untouched); for a model changed "
                                           "since that campaign started"),
        verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Run a calibration campaign as a Prefect flow and print the best case and the tables."""
    prefect_environment(verbose)
    from storage import ArtifactStore, EvaluationJournal

    storage = _folder("--storage", storage)
    c = _load(case)  # clear errors before any simulator time or Prefect start-up
    workers = _fit_workers(workers, c.simulator.cores_per_run, task_runner)
    _check_agent(agent, budget, workers)
    _check_runner(task_runner)
    if fork is not None:
        _check_fork(fork, campaign, storage.resolve())
    _start_api()
    from flows.campaign import campaign_flow
    from hmcore.calibration.registry import default_campaign_name

    name = campaign or default_campaign_name(c.name, agent, seed)
    storage = storage.resolve()
    forked_from = None
    if fork is not None:
        forked_from, name = campaign, fork
    try:
        from storage import refuse_links

        refuse_links(storage, name)
    except ValueError as exc:
        err_console.print(f"[red]x[/] {exc}", highlight=False)
        raise typer.Exit(2)
    console.print(f"campaign [bold]{name}[/]: case {c.name}, agent {agent}, budget {budget}, "
                  f"workers {workers}, seed {seed}, storage {storage}"
                  + (f", forked from {forked_from}" if forked_from else ""))
    flow_fn = campaign_flow
    try:
        done = len(EvaluationJournal(ArtifactStore(storage), name).indices())
        if done:  # (Prefect's INFO line saying so is not shown without --verbose)
            console.print(f"resuming campaign {name}: {done} calls already journaled")
        with Watch(console, campaign_poll(storage, name, budget), _columns("run"), total=budget,
                   initial={"best": "-"}):
            result = flow_fn(case=str(case), agent=agent, budget=budget, workers=workers,
                             seed=seed, storage=str(storage), campaign=name,
                             task_runner=task_runner, dask_address=dask_address,
                             **({"forked_from": forked_from} if forked_from else {}))
    except (ValueError, _flow_refused()) as exc:
        err_console.print(f"[red]x[/] {exc}")
        raise typer.Exit(2)
    _print_report(storage, result["campaign"], result)


def _check_fork(fork: str, campaign: Optional[str], storage: Path) -> None:
    """``--fork NEW`` needs the campaign it comes from (``--campaign OLD``, stored) and a new
    name; exit 2 with one line otherwise, before Prefect starts."""
    problem = None
    if campaign is None:
        problem = "--fork needs --campaign: the campaign the new one comes from"
    elif fork == campaign:
        problem = f"--fork {fork}: give a new campaign name, not the one it comes from"
    elif not (storage / campaign / "campaign.json").is_file():
        problem = f"--fork {fork}: there is no campaign '{campaign}' in {storage} to fork from"
    if problem:
        err_console.print(f"[red]x[/] {problem}", highlight=False)
        raise typer.Exit(2)


def _fit_workers(workers: int, threads: int, task_runner: str) -> int:
    """Local runs: at most as many simulator threads at once as the machine has cores
    (``threads``: cores one run uses, its threads x MPI processes)."""
    import os

    cores = os.cpu_count() or 1
    if task_runner != "threads" or workers * threads <= cores:
        return workers
    fitted = max(1, cores // threads)
    console.print(f"[yellow]note[/]: {workers} workers x {threads} cores per run would "
                  f"need {workers * threads} cores, this machine has {cores}: {fitted} "
                  f"worker(s)")
    return fitted


def _check_agent(agent: str, budget: int, workers: int) -> None:
    from hmcore.calibration.methods import METHODS, budget_problem

    if agent not in METHODS:
        err_console.print(f"[red]x[/] --agent must be one of {list(METHODS)}, got {agent!r}")
        raise typer.Exit(2)
    problem = budget_problem(agent, budget, workers)
    if problem:
        err_console.print(f"[red]x[/] --agent {agent}, --budget {budget}, --workers {workers}: "
                          f"{problem}")
        raise typer.Exit(2)


def _start_api() -> None:
    """The command's Prefect API: the configured server, or a temporary one that dies with
    hmflow (:mod:`hmflow.server`), stopped when the command ends. Call it after the input is
    checked and before Prefect is imported (Prefect reads its settings once, on import)."""
    from hmflow.server import temporary_api

    api = temporary_api()
    api.__enter__()  # (killed with hmflow if it dies)
    def stop() -> None:
        try:  # the run's last log lines reach the server before it stops
            from prefect.logging.handlers import APILogWorker

            APILogWorker.drain_all(timeout=5)
        except Exception:  # nothing to send, or Prefect never imported
            pass
        api.__exit__(None, None, None)
    ctx = _command_context()
    if ctx is not None:  # stopped when the command ends (also when it runs in-process)
        ctx.call_on_close(stop)
    else:
        import atexit

        atexit.register(stop)


def _command_context():
    """The running command's click context (Typer vendors click since 0.16), or None."""
    for module in ("typer._click.globals", "click.globals"):
        try:
            get = __import__(module, fromlist=["get_current_context"]).get_current_context
        except ImportError:
            continue
        ctx = get(silent=True)
        if ctx is not None:
            return ctx
    return None


def _flow_refused() -> type[Exception]:
    """What calling a flow that refused its input (a Failed state) raises; imported when an
    exception is being matched, so the CLI starts without Prefect."""
    from prefect.exceptions import FailedRun

    return FailedRun


def _check_runner(kind: str) -> None:
    from flows.runners import RUNNERS

    if kind not in RUNNERS:
        err_console.print(f"[red]x[/] --task-runner must be one of {list(RUNNERS)}, got {kind!r}")
        raise typer.Exit(2)


def _print_report(storage: Path, campaign: str, result: dict | None = None) -> None:
    """Print a stored report: best parameters, distance to truth, the paper's tables, then one
    summary table (best E, headline numbers, failed / penalised calls, where the report is).
    ``result``: the flow's result, whose ``report_html`` (else ``report_path``) is shown."""
    from storage import ArtifactStore

    store = ArtifactStore(storage)
    rep = store.latest(campaign, "report")
    doc = rep.read_json("report.json")
    best = doc.get("best")
    if doc["calls"]:
        console.print(f"\n[bold]{doc['campaign']}[/]: {doc['calls']} calls: "
                      f"{status_text(doc.get('status_counts'))}")
    else:
        console.print(f"\n[bold]{doc['campaign']}[/]: no calibration campaign under this name")
    if not best:
        if doc["calls"]:
            console.print("[red]no valid simulation - nothing to call best[/]")
    else:
        console.print(f"best call {best['index'] + 1} (calls numbered from 1): E = {best['E']:.6g}"
                      + (f", held-back E = {best['E_heldout']:.6g}" if best.get("E_heldout") else ""))
        for k, v in best["params"].items():
            console.print(f"  {k:<12} = {v:.4f}")
        for k, d in (doc.get("truth_distance") or {}).items():
            console.print(f"  {k:<12}   truth {d['truth']:.4f}, error {d['error']:+.4f} "
                          f"({100 * d['error_of_range']:.1f} % of range)")
        print_tables(store.latest(campaign, "best").read_json("metrics.json")["metrics"], "Best case:")
    diagnosis = doc.get("diagnosis")
    if diagnosis:
        console.print(f"diagnosis: selected {diagnosis['selected'] or 'none'}; "
                      f"{diagnosis['verdict']}", highlight=False)
    result = result or {}
    where = (result.get("report_html") or result.get("report_path")
             or rep.file("report.html" if "report.html" in rep.files else "report.md"))
    console.print(summary_table(doc, where))


@app.command()
def report(storage: Path = typer.Option(Path("./hmflow-storage"), "--storage"),
           campaign: str = typer.Option(..., "--campaign", callback=_checked_campaign),
           verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Rebuild a campaign's report from stored artifacts (zero simulator calls)."""
    prefect_environment(verbose)
    if not (storage / campaign).is_dir():
        err_console.print(f"[red]x[/] no campaign '{campaign}' in {storage}; known: "
                          f"{sorted(p.name for p in storage.iterdir()) if storage.is_dir() else []}")
        raise typer.Exit(2)
    _start_api()
    from flows.report import report_flow

    try:
        report_flow(storage=str(storage), campaign=campaign)
    except FileNotFoundError as exc:
        err_console.print(f"[red]x[/] {exc}")
        raise typer.Exit(2)
    _print_report(storage, campaign)


@app.command()
def tables(storage: Path = typer.Option(Path("./hmflow-storage"), "--storage"),
           campaign: str = typer.Option(..., "--campaign", callback=_checked_campaign),
           call: Optional[int] = typer.Option(None, "--call", min=1, help="Call number (from 1); "
                                              "default: the archived best case"),
           markdown_out: Optional[Path] = typer.Option(None, "--markdown", help="Also write the "
                                                       "tables as Markdown to this new file")) -> None:
    """The reference paper's three tables for a stored campaign, rescored from the stored
    summary with today's formulas (zero simulator calls)."""
    from hmcore.reporting.paper_tables import markdown, metrics_from_summary, paper_tables
    from storage import ArtifactStore, EvaluationJournal

    store = ArtifactStore(storage)
    case = store.latest(campaign, "case") if (storage / campaign).is_dir() else None
    if case is None:
        err_console.print(f"[red]x[/] no campaign '{campaign}' with a stored case in {storage}; "
                          f"known: {store.campaigns() if storage.is_dir() else []}")
        raise typer.Exit(2)
    if call is None:
        best = store.latest(campaign, "best")
        if best is None:
            err_console.print(f"[red]x[/] campaign '{campaign}' has no archived best case (no valid "
                              "run yet); give --call N")
            raise typer.Exit(2)
        run_dir, label = best.path, f"best case (call {best.read_json('metrics.json')['index'] + 1})"
    else:
        rows = {r["index"]: r for r in EvaluationJournal(store, campaign).rows()}
        if call - 1 not in rows:
            err_console.print(f"[red]x[/] campaign '{campaign}' has no call {call} (it has "
                              f"{len(rows)} calls, numbered from 1)")
            raise typer.Exit(2)
        run_dir, label = Path(rows[call - 1]["run_dir"]), f"call {call}"
    summaries = sorted(run_dir.glob("*.SMSPEC"))
    if not summaries:
        err_console.print(f"[red]x[/] {run_dir} holds no summary file (.SMSPEC): the run failed "
                          "or its files were removed")
        raise typer.Exit(2)
    doc = case.read_json("case.json")
    fit, held = metrics_from_summary(case.read_parquet("observed.parquet"), summaries[0],
                                     doc["wells"], doc["time_tolerance_days"],
                                     doc.get("history_end_days"))
    console.print(f"[bold]{campaign}[/]: {label}, {summaries[0]}")
    print_tables(fit, "Fitted history:")
    text = markdown(paper_tables(fit), f"{campaign}, {label}, fitted history")
    if held:
        print_tables(held, "Held-back history:")
        text += "\n" + markdown(paper_tables(held), f"{campaign}, {label}, held-back history")
    if markdown_out is not None:
        if markdown_out.exists():
            err_console.print(f"[red]x[/] {markdown_out} exists; hmflow never overwrites a file "
                              "(choose a new name)")
            raise typer.Exit(2)
        markdown_out.write_text(text)
        console.print(f"wrote {markdown_out}")


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
          storage: Path = typer.Option(Path("./hmflow-storage"), "--storage"),
          name: Optional[str] = typer.Option(None, "--name", help="Benchmark name (default "
                                             "bench-CASE); the same name resumes"),
          task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
          dask_address: Optional[str] = typer.Option(None, "--dask-address",
                                                     help=DASK_HELP),
          verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Equal-budget benchmark: every method x seed is an ordinary campaign (a stopped benchmark
    resumes where it was), then one table, Parquet files and a best-so-far plot."""
    prefect_environment(verbose)
    storage = _folder("--storage", storage)
    c = _load(case)
    workers = _fit_workers(workers, c.simulator.cores_per_run, task_runner)
    chosen = list(AGENTS) if methods == "all" else [m.strip() for m in methods.split(",")
                                                    if m.strip()]
    unknown = [m for m in chosen if m not in METHODS]
    if unknown or not chosen:
        err_console.print(f"[red]x[/] --methods: unknown {unknown or 'none given'}; choose from "
                          f"{list(METHODS)}")
        raise typer.Exit(2)
    for m in chosen:
        _check_agent(m, budget, workers)
    _check_runner(task_runner)
    _start_api()
    from flows.bench import bench_flow, bench_names

    storage = storage.resolve()
    console.print(f"benchmark on case {c.name}: {len(chosen)} methods x {seeds} seeds x {budget} "
                  f"calls, {workers} workers, storage {storage}")
    flow_fn = bench_flow
    bench_name, _, campaigns = bench_names(c.name, chosen, list(range(seeds)), name)
    try:
        with Watch(console, bench_poll(storage, campaigns, budget, workers, bench_name),
                   _columns("bench"),
                   total=len(campaigns) * budget, initial={"current": "starting"}):
            result = flow_fn(case=str(case), methods=chosen, seeds=list(range(seeds)),
                             budget=budget, workers=workers, storage=str(storage), name=name,
                             task_runner=task_runner, dask_address=dask_address)
    except (ValueError, _flow_refused()) as exc:
        err_console.print(f"[red]x[/] {exc}")
        raise typer.Exit(2)
    console.print(Path(result["summary_path"]).read_text(), highlight=False, soft_wrap=True)
    console.print(f"table: {result['summary_path']}\nplot:  {result['plot_path']}")


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
           storage: Path = typer.Option(Path("./hmflow-storage"), "--storage",
                                        help="Artifact store (made absolute)"),
           campaign: Optional[str] = typer.Option(None, "--campaign", callback=_checked_campaign, help="Campaign name "
                                                  "(default CASE-AGENT-seedS)"),
           no_report: bool = typer.Option(False, "--no-report", help="Skip the report-only "
                                          "deployment"),
           task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
           dask_address: Optional[str] = typer.Option(None, "--dask-address", help=DASK_HELP),
           list_: bool = typer.Option(False, "--list", help="List hmflow's deployments on the "
                                      "server and exit")) -> None:
    """Deploy the campaign on a schedule (and its report-only rerun) to a Prefect server's
    process work pool; a worker started with `prefect worker start --pool POOL` runs them."""
    from prefect.settings import PREFECT_API_URL

    from deployments import campaign as dep

    if not PREFECT_API_URL.value():
        err_console.print("[red]x[/] no Prefect server configured (PREFECT_API_URL is not set): "
                          "deployments on a temporary server would vanish with it. Start one "
                          "with `prefect server start`, then `prefect config set "
                          "PREFECT_API_URL=http://127.0.0.1:4200/api`")
        raise typer.Exit(2)
    if list_:
        rows = dep.list_deployments()
        t = Table(title=f"hmflow deployments on {PREFECT_API_URL.value()}")
        for col in ("deployment", "schedule", "pool", "paused", "campaign", "agent", "budget"):
            t.add_column(col)
        for d in rows:
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
    from hmcore.calibration.methods import METHODS, budget_problem

    if agent not in METHODS:
        problems.append(f"--agent must be one of {list(METHODS)}, got {agent!r}")
    elif budget_problem(agent, budget, workers):
        problems.append(budget_problem(agent, budget, workers))
    from flows.runners import RUNNERS

    if task_runner not in RUNNERS:
        problems.append(f"--task-runner must be one of {list(RUNNERS)}, got {task_runner!r}")
    if dask_address and task_runner != "dask":
        problems.append("--dask-address needs --task-runner dask")
    if problems:
        for p_ in problems:
            err_console.print(f"[red]x[/] {p_}")
        raise typer.Exit(2)
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


KINDS_HELP = ("Families of candidate extensions to search, comma-separated (default all): "
              "well_skin, regional_permeability, layer_permeability, vertical_permeability, "
              "aquifer_strength, fault_transmissibility, relative_permeability, "
              "productivity_change")
"""Spelled out so that ``--help`` does not import the diagnosis; a test holds it to
:data:`hmcore.diagnosis.extensions.KINDS`, as ``GENERATORS_HELP`` to the generators."""
GENERATORS_HELP = ("partial_fault, offcentre_region, relperm_endpoint, relperm_scaling, "
                   "two_kinds, contact, pvt, dated_productivity, late_productivity")


@app.command()
def diagnose(case: Optional[str] = typer.Option(None, "--case", help=CASE_HELP + " Default: "
                                                 "the --from-campaign's case, else 'synthetic'."),
             storage: Path = typer.Option(Path("./hmflow-storage"), "--storage",
                                          help="Artifact store"),
             budget: Optional[int] = typer.Option(None, "--budget", min=1, help="Cap on simulator "
                                                  "calls (default: as many as the steps need)"),
             workers: int = typer.Option(2, "--workers", min=1, help="Simulations at once"),
             campaign: Optional[str] = typer.Option(None, "--campaign", callback=_checked_campaign, help="Name the diagnosis "
                                                    "is stored under (default: the "
                                                    "--from-campaign, else CASE-diagnosis)"),
             from_campaign: Optional[str] = typer.Option(
                 None, "--from-campaign", callback=_checked_campaign, help="Start from this stored campaign's best "
                 "parameters instead of calibrating the case's parameters first"),
             task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
             dask_address: Optional[str] = typer.Option(None, "--dask-address",
                                                        help=DASK_HELP),
             kinds: Optional[str] = typer.Option(None, "--kinds", help=KINDS_HELP),
             verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Find what the calibrated model gets wrong, name the cause, extend the model, measure the
    gain on the fitted and the held-back history; writes diagnosis.json (path printed)."""
    prefect_environment(verbose)
    _check_runner(task_runner)
    kind_list = _diagnosis_kinds(kinds, task_runner, dask_address)
    if case:
        _diagnosis_budget(_load(case), budget, kind_list, from_campaign is not None)
    _start_api()
    from flows.diagnose import (campaign_start, default_campaign_name, diagnose_flow,
                                print_diagnosis)

    calibrated = None
    if from_campaign:
        from storage import ArtifactStore

        try:
            case, calibrated = campaign_start(ArtifactStore(storage.resolve()), from_campaign,
                                              case)
        except (LookupError, ValueError, CaseError) as exc:
            err_console.print(f"[red]x[/] {exc}", highlight=False)
            raise typer.Exit(2)
        campaign = campaign or from_campaign  # the diagnosis goes into that campaign's report
    case = case or "synthetic"
    c = _load(case)  # clear errors before any simulator time or Prefect start-up
    _diagnosis_budget(c, budget, kind_list, calibrated is not None)
    storage = storage.resolve()
    # what flows.diagnose.diagnose_command does, with a progress display until the flow ends
    flow_fn = diagnose_flow
    poll = diagnosis_poll(storage, campaign or default_campaign_name(c.name))
    try:
        with Watch(console, poll, _columns("diagnose" if budget else "diagnose-open"),
                   total=budget, initial={"step": "-"}):
            result = flow_fn(case=str(case), storage=str(storage), budget=budget,
                             campaign=campaign, workers=workers, calibrated=calibrated,
                             task_runner=task_runner, dask_address=dask_address,
                             kinds=list(kind_list) if kind_list else None)
    except (ValueError, _flow_refused()) as exc:
        err_console.print(f"[red]x[/] {exc}")
        raise typer.Exit(2)
    print_diagnosis(result, console)


def _diagnosis_kinds(kinds: Optional[str], task_runner: str,
                     dask_address: Optional[str]) -> Optional[tuple[str, ...]]:
    """``--kinds`` as the families it names (None: all); exit 2 with every problem of the
    diagnose options that need no case (an unknown kind, with a suggestion)."""
    from hmcore.diagnosis.settings import parse_kinds

    problems, names = [], None
    if kinds is not None:
        try:
            names = parse_kinds(kinds, "--kinds")
        except ValueError as exc:
            problems += str(exc).split("; ")
    if dask_address and task_runner != "dask":
        problems.append("--dask-address needs --task-runner dask")
    if problems:
        for p_ in problems:
            err_console.print(f"[red]x[/] {p_}", highlight=False)
        raise typer.Exit(2)
    return names


def _diagnosis_budget(case, budget: Optional[int], kinds: Optional[tuple[str, ...]],
                      given: bool) -> None:
    """Exit 2 with one line when ``--budget`` cannot cover the diagnosis's minimum (see
    :func:`hmcore.diagnosis.workflow.minimum_runs`), before any simulator time."""
    if budget is None:
        return
    from hmcore.diagnosis.settings import DiagnosisSettings
    from hmcore.diagnosis.workflow import budget_problem

    settings = DiagnosisSettings(budget=budget, **({"kinds": kinds} if kinds else {}))
    problem = budget_problem(case, settings, given, "--budget")
    if problem:
        err_console.print(f"[red]x[/] {problem}", highlight=False, soft_wrap=True)
        raise typer.Exit(2)


@app.command()
def hide(out: Path = typer.Option(..., "--out", help="New directory for the case (must not "
                                  "exist or be empty)"),
         kind: Optional[str] = typer.Option(None, "--kind", help="Kind of the hidden effect, "
                                            "drawn by --seed: a library kind, or a generator "
                                            f"of effects beyond the library ({GENERATORS_HELP}"
                                            "); omit: a control, nothing hidden"),
         seed: int = typer.Option(0, "--seed", help="Draws the effect, its strength and the "
                                  "noise (and, for the synthetic case, the fields)"),
         candidate: Optional[str] = typer.Option(None, "--candidate", help="Hide this library "
                                                 "candidate instead of drawing one, e.g. "
                                                 "'regional_permeability:PROD2'"),
         value: Optional[float] = typer.Option(None, "--value", help="Its value (default: drawn "
                                               "from the kind's realistic range)"),
         deck: Optional[Path] = typer.Option(None, "--deck", help="Base deck (default: the "
                                             "built-in synthetic reservoir of --seed)"),
         set_: list[str] = typer.Option([], "--set", help="NAME=VALUE of the five global "
                                        "parameters in the truth (with --deck; default "
                                        "multipliers 1, the deck's skin)"),
         history_end: Optional[float] = typer.Option(None, "--history-end", help="Days fitted "
                                                     "(default: 75 % of the record)"),
         record_end: Optional[float] = typer.Option(None, "--record-end", help="Last day of the "
                                                    "measured record (default: the schedule's "
                                                    "end; with --deck)"),
         sigma: bool = typer.Option(False, "--sigma/--no-sigma", help="Write the noise sigma "
                                    "into the CSV (default: no, the diagnosis estimates it)")
         ) -> None:
    """Write a case whose "measured" history hides one model extension the base model lacks
    (the truth run + realistic correlated noise), to try `hmflow diagnose` on, then `hmflow
    reveal` to see whether it found it. The effect is recorded in OUT/hidden_effect.json."""
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.diagnosis.extensions import KINDS, base_values
    from hmcore.scenarios.generators import GENERATORS
    from hmcore.scenarios.effects import chosen_effect
    from hmcore.scenarios.generators import draw_effect, draw_effects
    from hmcore.scenarios.hidden import (synthetic_deck_info, write_hidden_deck_case, write_hidden_synthetic_case)
    from hmcore.model.parameters import ParameterSpace

    problems = []
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        problems.append(f"--out {out}: exists and is not an empty directory; nothing is "
                        "overwritten, choose a new one")
    if kind is not None and kind not in KINDS + GENERATORS:
        problems.append(f"--kind {kind!r}: unknown; one of {list(KINDS)} or a generator "
                        f"{list(GENERATORS)}")
    if kind in GENERATORS and candidate is not None:
        problems.append(f"--candidate names a library candidate; --kind {kind} generates "
                        "effects beyond the library: give one of them, not both")
    if candidate is not None and kind is not None and not candidate.startswith(kind + ":"):
        problems.append(f"--candidate {candidate!r} is not of --kind {kind!r}")
    if value is not None and candidate is None:
        problems.append("--value needs --candidate (which parameter it is the value of)")
    if deck is not None and not deck.is_file():
        problems.append(f"--deck {deck}: no such file")
    if deck is None and (set_ or record_end is not None):
        problems.append("--set and --record-end apply to --deck cases (the synthetic case has "
                        "its own known truth)")
    if problems:
        for p_ in problems:
            err_console.print(f"[red]x[/] {p_}")
        raise typer.Exit(2)
    space = ParameterSpace.reference()
    created = not out.exists()
    try:
        if deck is None:
            from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH

            truth = dict(SYNTHETIC_TRUTH)
            info = synthetic_deck_info(seed, out / "base-deck")
        else:
            info = DeckInfo.inspect(deck.resolve())
            truth = {**base_values(info, space), **parse_sets(set_, space.names)}
        effect = None
        k = kind or (candidate.split(":", 1)[0] if candidate else None)
        if candidate is not None and value is not None:
            effect = chosen_effect(candidate, value, info, space, truth)
        elif k in GENERATORS:
            draw_effects(k, seed, info, space, truth)  # an impossible one refused here
        elif k is not None:
            effect = draw_effect(k, seed, info, space, truth,
                                 choices=[candidate] if candidate else None)
        generated = k if k in GENERATORS else None
        if deck is None:
            case_toml, effect = write_hidden_synthetic_case(
                out, seed, kind=generated, effect=effect, history_end_days=history_end)
            text = case_toml.read_text().replace('name = "synthetic"', f'name = "{out.name}"', 1)
            case_toml.write_text(text)
        else:
            case_toml, effect = write_hidden_deck_case(
                out, deck, seed, truth=truth, kind=generated, effect=effect,
                history_end_days=history_end, with_sigma=sigma, name=out.name,
                end_days=record_end)
    except ValueError as exc:
        if created:  # leave nothing half-written behind
            import shutil

            shutil.rmtree(out, ignore_errors=True)
        err_console.print(f"[red]x[/] {exc}")
        raise typer.Exit(2)
    hidden_json = out / "hidden_effect.json"
    n = len(json.loads(hidden_json.read_text()).get("effects") or [])
    what = ("nothing (a control)" if effect is None else f"one {effect.kind} effect" if n == 1
            else f"{n} effects")
    if kind in GENERATORS:
        what += f", generated by {kind} (beyond the library's own geometry)"
    signal = json.loads(hidden_json.read_text()).get("signal")
    for line in (f"[green]Case written[/]: {case_toml}",
                 f"  hidden: {what}; the details are in {hidden_json} (look after diagnosing)",
                 *([f"  signal: {_signal_text(signal)}"] if signal else []),
                 f"  next:   hmflow diagnose --case {case_toml}",
                 f"          hmflow reveal --hidden {hidden_json} --diagnosis <the "
                 "diagnosis.json it prints>"):
        console.print(line, soft_wrap=True, highlight=False)


@app.command()
def reveal(hidden: Path = typer.Option(..., "--hidden", help="hidden_effect.json of a case "
                                       "written by `hmflow hide`"),
           diagnosis: Path = typer.Option(..., "--diagnosis", help="diagnosis.json written by "
                                          "`hmflow diagnose`")) -> None:
    """Compare a diagnosis with the effect hidden in its case: right kind and well / layer
    ranked first, selected, held-back misfit improved. Exit 1 when it was not found."""
    from hmcore.scenarios.judge import judge, judge_effects
    from hmcore.scenarios.effects import load_hidden_effects

    for label, path in (("--hidden", hidden), ("--diagnosis", diagnosis)):
        if not path.is_file():
            err_console.print(f"[red]x[/] {label} {path}: no such file")
            raise typer.Exit(2)
    effects = load_hidden_effects(hidden)
    doc = json.loads(diagnosis.read_text())
    signal = json.loads(hidden.read_text()).get("signal")
    if len(effects) > 1 or (effects and effects[0].generated):
        j = judge_effects(doc, effects, signal)
        for e in effects:
            console.print(f"hidden: [bold]{e.candidate.id}[/] = {e.value:.4g} "
                          f"({e.candidate.description}); a right answer: {e.kind}"
                          + (f" at {', '.join(e.candidate.details['expect_wells'])}"
                             if e.candidate.details.get("expect_wells") else "")
                          + (" over cells i {}-{}, j {}-{} (sharing a quarter or more of "
                             "the columns the two boxes cover)".format(
                              *e.parameter.box[:4]) if e.kind == "regional_permeability"
                             and e.parameter.box else "")
                          + f" - {'[green]named[/]' if j['named'][e.candidate.id] else '[red]not named[/]'}")
        console.print(f"accepted: {', '.join(j['accepted']) or 'none'}; first cause: "
                      f"{doc['causes'][0]['id']}")
        g = doc["gain"]
        console.print(f"held-back E {_num(g['heldout_before'], 5)} -> "
                      f"{_num(g['heldout_after'], 5)}")
        console.print("[bold green]FOUND[/]" if j["found"] else "[bold red]NOT FOUND[/]")
        if not j["found"]:
            raise typer.Exit(1)
        return
    effect = effects[0] if effects else None
    j = judge(doc, effect, signal)
    if effect is None:
        console.print("hidden: nothing (a control)")
    else:
        console.print(f"hidden: [bold]{effect.candidate.id}[/] = {effect.value:.4g} "
                      f"({effect.candidate.description})")
    first = doc["causes"][0]
    console.print(f"ranked first: [bold]{first['id']}[/] - {first['description']}")
    console.print(f"selected: {doc['selected']['id'] if doc['selected'] else 'none'}")
    console.print(f"ranking: {', '.join(j['ranking'])}")
    g = doc["gain"]
    console.print(f"held-back E {_num(g['heldout_before'], 5)} -> {_num(g['heldout_after'], 5)}"
                  + (f" (the truth itself: {_num(j['truth_E_heldout'], 5)})"
                     if j.get("truth_E_heldout") is not None else ""))
    if j.get("heldout_improved") and not j.get("heldout_E_improved"):
        console.print("  the truth scores no better held-back E than the calibrated model: the "
                      "noise decides E there, so the noise-weighted held-back misfit counts "
                      f"(whitened SSR {_num(g['ssr_heldout_before'], 0)} -> "
                      f"{_num(g['ssr_heldout_after'], 0)})", highlight=False)
    if signal:
        console.print(f"signal of the hidden effect: {_signal_text(signal)}", highlight=False)
    checks = ("ranked_first", "selected", "heldout_improved")
    console.print("  ".join(f"{c}: {'[green]yes[/]' if j[c] else '[red]no[/]'}" for c in checks))
    console.print("[bold green]FOUND[/]" if j["found"] else "[bold red]NOT FOUND[/]")
    if not j["found"]:
        raise typer.Exit(1)


def _signal_text(signal: dict) -> str:
    """One line on how strongly a hidden effect shows in the data (see
    :func:`hmcore.scenarios.hidden.effect_signal`)."""
    if "error" in signal:
        return signal["error"]
    text = (f"chi2 {signal['chi2_fit']:.0f} on the fitted history ({signal['n_fit']} points, "
            f"days <= {signal['history_end_days']:g}), {signal['chi2_heldout']:.0f} on the "
            f"held-back ({signal['n_heldout']} points), before the global parameters absorb any")
    if "chi2_fit_after_globals" in signal:
        text += (f"; {signal['chi2_fit_after_globals']:.0f} on the fitted history (held back "
                 f"{signal['chi2_heldout_after_globals']:.0f}) once the global parameters "
                 "absorb what they can")
    if not signal["visible_in_fitted_history"]:
        text += ("; the fitted history hardly shows it, so no diagnosis can be expected to name "
                 "it from there (fit a longer history)")
    return text


def main() -> None:  # pragma: no cover - console entry
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
