"""The ``hmflow`` command line: check, evaluate, run, report, diagnose.

``check`` and ``evaluate`` use hmcore alone; ``run``, ``report`` and ``diagnose`` start the
Prefect flows in ``flows/`` (an ephemeral Prefect server is used when none is configured).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from hmcore.errors import CaseError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Batch history matching of reservoir models with OPM Flow.")
console = Console()
err_console = Console(stderr=True)

CASE_HELP = "Case TOML file, or the built-in name 'synthetic' (generated on first use)."


def _load(case: str):
    from hmcore.case import load_case

    try:
        return load_case(case)
    except CaseError as exc:
        err_console.print(f"[bold red]Case {case} is not valid[/] - {len(exc.problems)} problem(s):")
        for p in exc.problems:
            err_console.print(f"  [red]x[/] {p.where}\n      {p.what}" + (f"\n      fix: {p.fix}" if p.fix else ""),
                              highlight=False)
        raise typer.Exit(2)


def _num(v, digits=4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}f}"


def print_tables(metrics: dict, title: str = "") -> None:
    """Print the paper's two tables (category table; well x response C_match)."""
    from hmcore.metrics import CATEGORIES, category_table, well_table

    t = Table(title=f"{title} match by category".strip())
    for col in ("category", "N", "NMSE", "R2", "C_match %"):
        t.add_column(col, justify="right" if col != "category" else "left")
    for row in category_table(metrics).itertuples(index=False):
        t.add_row(row.category, str(row.N), _num(row.NMSE), _num(row.R2), _num(row.C_match, 2))
    console.print(t)
    w = Table(title=f"{title} C_match (%) per well and response".strip())
    w.add_column("well")
    for c in CATEGORIES:
        w.add_column(c, justify="right")
    for row in well_table(metrics).itertuples(index=False):
        w.add_row(row[0], *[_num(v, 2) for v in row[1:]])
    console.print(w)


def parse_sets(sets: list[str], names: list[str]) -> dict[str, float]:
    values = {}
    problems = []
    for item in sets:
        name, sep, val = item.partition("=")
        if not sep:
            problems.append(f"--set {item!r}: expected NAME=VALUE")
            continue
        if name not in names:
            problems.append(f"--set {item!r}: unknown parameter {name!r}; known: {names}")
            continue
        try:
            values[name] = float(val)
        except ValueError:
            problems.append(f"--set {item!r}: {val!r} is not a number")
    if problems:
        for p in problems:
            err_console.print(f"[red]x[/] {p}")
        raise typer.Exit(2)
    return values


@app.command()
def check(case: str = typer.Option("synthetic", "--case", help=CASE_HELP)) -> None:
    """Validate the case (deck, history, parameters); runs no simulation."""
    c = _load(case)
    obs = c.observed
    console.print(f"[green]OK[/] case [bold]{c.name}[/] ({c.source})")
    console.print(f"  deck      {c.deck}: grid {'x'.join(map(str, c.info.dims))}, "
                  f"{c.info.nactive} active cells, wells {sorted(c.info.wells)}, "
                  f"schedule {c.info.end_days:g} days")
    counts = obs.groupby("quantity").size().to_dict()
    derived = obs[obs.derived].groupby("quantity").size().to_dict()
    console.print(f"  history   {c.observed_path}: {len(obs[~obs.derived])} rows {counts}"
                  + (f", derived {derived}" if derived else ""))
    console.print(f"  fitting   days <= {c.history_end_days if c.history_end_days else 'end'}, "
                  f"tolerance {c.time_tolerance_days:g} d, misfit {c.misfit.variant}")
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
    from hmcore.evaluation import evaluate as run_one
    from hmcore.report import metrics_document
    from hmcore.simulator import make_simulator

    c = _load(case)
    values = parse_sets(set_, c.space.names)
    bounds = c.space.check_in_bounds(values)
    if bounds:
        console.print(f"[yellow]note[/]: {'; '.join(bounds)} (evaluated anyway)")
    if out.exists() and any(out.iterdir()):
        err_console.print(f"[red]x[/] {out} exists and is not empty; hmflow never overwrites results "
                          "(choose a new --out)")
        raise typer.Exit(2)
    out.mkdir(parents=True, exist_ok=True)
    sim = make_simulator(simulator or c.simulator.backend, c.simulator.timeout_s)
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
    console.print(f"wrote {out / 'metrics.json'} and {out / 'responses.parquet'}")
    if ev.status.value == "FAIL":
        raise typer.Exit(1)


def main() -> None:  # pragma: no cover - console entry
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
