"""``hmflow run``, ``report`` and ``tables``: a calibration campaign as a Prefect flow, its
report rebuilt from storage, and the paper's tables of a stored call."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from flows.inputs import scalar_problems
from hmcore.calibration.posterior import DEFAULT_DRAWS, MIN_BUDGET
from hmcore.calibration.registry import DEFAULT_AGENT, default_campaign_name
from hmflow.cli.common import (
    CASE_HELP,
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
    no_campaign,
    print_forecast,
    print_tables,
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
    progress_columns,
    quiet_storage_faults,
    start_api,
)
from hmflow.console import Watch, campaign_poll, prefect_environment, status_text, summary_table

CAMPAIGN_HELP = ("Campaign name; the same name resumes. Default: CASE-AGENT-vN-seedS (the "
                 "case's name, --agent, the method's version N, left out for version 1, and "
                 "--seed); with the defaults: "
                 f"{default_campaign_name('synthetic', DEFAULT_AGENT, 0)}. Printed when the "
                 "run starts and ends")
"""``run --help`` on the campaign name, with the name of the default run made by the rule
itself (:func:`~hmcore.calibration.registry.default_campaign_name`)."""


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
        storage: Path = typer.Option(DEFAULT_STORAGE, "--storage", help="Artifact store"),
        campaign: Optional[str] = typer.Option(None, "--campaign", callback=checked_campaign,
                                               help=CAMPAIGN_HELP),
        task_runner: str = typer.Option("threads", "--task-runner", help=RUNNER_HELP),
        dask_address: Optional[str] = typer.Option(None, "--dask-address", help=DASK_HELP),
        cluster: Optional[str] = typer.Option(None, "--cluster", help=CLUSTER_HELP),
        fork: Optional[str] = typer.Option(None, "--fork", callback=checked_campaign,
                                           help="Start a new campaign FORK on the case as it "
                                           "is now, recording that it comes from --campaign "
                                           "(which is left untouched); for a model changed "
                                           "since that campaign started"),
        forecast_draws: Optional[int] = typer.Option(
            None, "--forecast-draws", min=0, help="Parameter sets drawn from the posterior at "
            "the best call and simulated after the fit, apart from the budget, for the "
            f"forecast (default {DEFAULT_DRAWS} when the budget is at least {MIN_BUDGET} calls; "
            "first one finite-difference run per parameter at the best call when the method "
            "left no Jacobian there; 0: the forecast is the best calls' spread)"),
        verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Run a calibration campaign as a Prefect flow and print the best case and the tables."""
    prefect_environment(verbose)
    task_runner = batch_runner(cluster, task_runner, dask_address)
    # storage imports pandas: keeps `hmflow --help` fast
    from storage import ArtifactStore, EvaluationJournal, refuse_links

    storage = folder("--storage", storage)
    if fork is not None:  # names only: refused before anything is written in the store
        check_fork(fork, campaign, storage.resolve())
    if campaign is not None:  # the name known: refused before the case is read
        hold_name(storage.resolve(), fork or campaign, "campaign")
    c = load_case(case)  # clear errors before any simulator time or Prefect start-up
    refuse(scalar_problems(c, latent=True))
    check_cluster(c, task_runner, storage.resolve())
    workers = fit_workers(workers, c.simulator.cores_per_run, task_runner)
    check_inputs(agent, budget, workers, task_runner)
    name = campaign or default_campaign_name(c.name, agent, seed)
    storage = storage.resolve()
    forked_from = None
    if fork is not None:
        forked_from, name = campaign, fork
    try:
        refuse_links(storage, name)
    except ValueError as exc:
        fail(str(exc))
    hold_name(storage, name, "campaign")  # (again: a no-op) before Prefect or any call
    start_api()
    # Prefect: only after start_api (it reads its settings on import)
    from flows.campaign import campaign_flow

    console.print(f"campaign [bold]{name}[/]: case {c.name}, agent {agent}, budget {budget}, "
                  f"workers {workers}, seed {seed}"
                  + (f", forked from {forked_from}" if forked_from else ""), highlight=False)
    console.print(f"storage: {escape(str(storage))}", soft_wrap=True, highlight=False)  # never broken
    quiet_storage_faults(storage)  # said in one line below, not as a traceback
    journal = EvaluationJournal(ArtifactStore(storage), name)
    with one_line_failures(storage):
        try:
            done = len(journal.indices())
            if done:  # (Prefect's INFO line saying so is not shown without --verbose)
                console.print(f"resuming campaign {name}: {done} calls already journaled")
            with Watch(console, campaign_poll(storage, name, budget), progress_columns("run"),
                       total=budget, initial={"best": "-"}):
                result = campaign_flow(case=str(case), agent=agent, budget=budget,
                                       workers=workers, seed=seed, storage=str(storage),
                                       campaign=name, task_runner=task_runner,
                                       dask_address=dask_address,
                                       forecast_draws=forecast_draws,
                                       **({"forked_from": forked_from} if forked_from else {}))
        except KeyboardInterrupt:
            console.print(f"campaign [bold]{name}[/] stopped with {len(journal.indices())} "
                          "calls journaled; the same command resumes it")
            raise
    print_report(storage, result["campaign"], result)
    console.print(f"campaign [bold]{result['campaign']}[/] done; to print its report again:",
                  highlight=False)
    again = ["hmflow", "report", "--campaign", result["campaign"]]
    if storage != DEFAULT_STORAGE.resolve():
        again += ["--storage", str(storage)]
    console.print("  " + escape(shlex.join(again)), soft_wrap=True,
                  highlight=False)  # a command to copy: never broken


def check_fork(fork: str, campaign: Optional[str], storage: Path) -> None:
    """``--fork NEW`` needs the campaign it comes from (``--campaign OLD``, stored) and a new
    name; exit 2 with one line otherwise, before Prefect starts."""
    if campaign is None:
        fail("--fork needs --campaign: the campaign the new one comes from")
    if fork == campaign:
        fail(f"--fork {fork}: give a new campaign name, not the one it comes from")
    if not (storage / campaign / "campaign.json").is_file():
        fail(f"--fork {fork}: there is no campaign '{campaign}' in {storage} to fork from")


def print_report(storage: Path, campaign: str, result: dict | None = None) -> None:
    """Print a stored report: best parameters, distance to truth, the paper's tables, then one
    summary table (best E, headline numbers, failed / penalised calls) and where the report
    is, on a line of its own that is never wrapped (a path broken at the terminal's width
    cannot be copied). ``result``: the flow's result, whose ``report_html`` (else
    ``report_path``) is shown."""
    # storage imports pandas: keeps `hmflow --help` fast
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
        chosen = best.get("chosen_by", "E")
        lk = best.get("likelihood")
        console.print(f"best call {best['index'] + 1} (calls numbered from 1), chosen by "
                      f"{chosen}: E = {best['E']:.6g}"
                      + (f", likelihood (chi2/n) = {lk:.6g}" if lk is not None else "")
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
    console.print(summary_table(doc, None))
    console.print(f"report: {escape(str(where))}", soft_wrap=True, highlight=False)  # never broken


@app.command()
def report(storage: Path = typer.Option(DEFAULT_STORAGE, "--storage"),
           campaign: str = typer.Option(..., "--campaign", callback=checked_campaign),
           verbose: bool = typer.Option(False, "--verbose", help=VERBOSE_HELP)) -> None:
    """Rebuild a campaign's report from stored artifacts (zero simulator calls)."""
    prefect_environment(verbose)
    if not (storage / campaign).is_dir():
        fail(no_campaign(campaign, storage), soft_wrap=True)
    start_api()
    # Prefect: only after start_api (it reads its settings on import)
    from flows.report import report_flow

    try:
        result = report_flow(storage=str(storage), campaign=campaign)
    except FileNotFoundError as exc:
        fail(str(exc))
    if result["kind"] == "ensemble":
        print_forecast(storage, campaign)
        console.print(f"report: {result['report_html']}", highlight=False, soft_wrap=True)
        return
    print_report(storage, campaign)


@app.command()
def tables(storage: Path = typer.Option(DEFAULT_STORAGE, "--storage"),
           campaign: str = typer.Option(..., "--campaign", callback=checked_campaign),
           call: Optional[int] = typer.Option(None, "--call", min=1, help="Call number (from 1); "
                                              "default: the archived best case"),
           markdown_out: Optional[Path] = typer.Option(None, "--markdown", help="Also write the "
                                                       "tables as Markdown to this new file")) -> None:
    """The reference paper's three tables for a stored campaign, rescored from the stored
    summary with today's formulas, and for the best case what the data pin down there: each
    parameter's sd and 95 % interval, the pairs the data cannot separate and the parameters
    they do not inform (zero simulator calls)."""
    # the reporting and storage import pandas: keeps `hmflow --help` fast
    from hmcore.reporting.paper_tables import markdown, metrics_from_summary, paper_tables
    from storage import ArtifactStore, EvaluationJournal

    store = ArtifactStore(storage)
    if not (storage / campaign).is_dir():
        fail(no_campaign(campaign, storage), soft_wrap=True)
    case = store.latest(campaign, "case")
    if case is None:
        fail(f"campaign '{campaign}' in {storage} has no stored case to rescore its runs "
             "against", soft_wrap=True)
    if call is None:
        best = store.latest(campaign, "best")
        if best is None:
            fail(f"campaign '{campaign}' has no archived best case (no valid run yet); give "
                 "--call N")
        run_dir, label = best.path, f"best case (call {best.read_json('metrics.json')['index'] + 1})"
    else:
        rows = {r["index"]: r for r in EvaluationJournal(store, campaign).rows()}
        if call - 1 not in rows:
            fail(f"campaign '{campaign}' has no call {call} (it has {len(rows)} calls, "
                 "numbered from 1)")
        run_dir, label = Path(rows[call - 1]["run_dir"]), f"call {call}"
    summaries = sorted(run_dir.glob("*.SMSPEC"))
    if not summaries:
        fail(f"{run_dir} holds no summary file (.SMSPEC): the run failed or its files were "
             "removed")
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
    if call is None:
        text += "\n" + print_identifiability(store, campaign, doc.get("source", "CASE"))
    if markdown_out is not None:
        if markdown_out.exists():
            fail(f"{markdown_out} exists; hmflow never overwrites a file (choose a new name)")
        markdown_out.write_text(text)
        console.print(f"wrote {markdown_out}")


CORRELATIONS_SHOWN = 8
"""``hmflow tables`` prints the correlation matrix of at most this many parameters (wider, it
points to the report)."""


def print_identifiability(store, campaign: str, case_source: str) -> str:
    """Print what the data pin down at a stored campaign's best call (the report's
    identifiability section as text tables and sentences); its Markdown."""
    # the reporting imports pandas: keeps `hmflow --help` fast
    from rich.table import Table

    from hmcore.reporting.identifiability import (
        correlation_frame,
        hint,
        identifiability_markdown,
        load_identifiability,
        pair_sentences,
        parameter_frame,
        uninformed_sentences,
    )

    finding = load_identifiability(store, campaign)
    if finding is None:
        return ""
    found = finding.result
    if found is None:
        console.print(f"Identifiability not computed. {finding.reason}", highlight=False)
        console.print("To get one, a least-squares campaign:", highlight=False)
        console.print("  " + escape(hint(case_source)), soft_wrap=True, highlight=False)
        return "\n".join(identifiability_markdown(finding, case_source, level=2)) + "\n"
    post = found.laplace
    base = finding.stencil.base
    where = ("the best call" if base == finding.best_index
             else f"call {base + 1}, {finding.stencil.distance:.3g} scaled units from it")
    title = (f"Identifiability at the best call (call {finding.best_index + 1}): Laplace "
             f"approximation, Jacobian at {where}; chi2/(n - d) = {post.s2:.4g}, sd not "
             "scaled by it")

    def table(head: str, df) -> Table:
        out = Table(title=head)
        for col in df.columns:
            out.add_column(str(col), justify="left" if col in ("parameter", "note")
                           else "right", overflow="fold")
        for row in df.itertuples(index=False):
            out.add_row(*map(str, row))
        return out

    console.print(table(title, parameter_frame(found)))
    if len(found.names) <= CORRELATIONS_SHOWN:
        console.print(table("correlations (scaled coordinates)", correlation_frame(found)))
    else:
        console.print(f"(the correlation matrix of the {len(found.names)} parameters: in the "
                      "campaign's report)", highlight=False)
    for sentence in pair_sentences(found) + uninformed_sentences(found) or [
            "The data separate every pair and inform every parameter."]:
        console.print(sentence, highlight=False)
    return "\n".join(identifiability_markdown(finding, case_source, level=2)) + "\n"
