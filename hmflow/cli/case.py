"""``hmflow init``, ``check`` and ``evaluate``: start a case for a deck, validate a case, run and
score one simulation. hmcore alone, no Prefect."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from hmcore.errors import CaseError
from hmcore.scoring.noise_table import case_noise_text
from hmcore.simulation import simulator as simulators
from hmcore.units import deck_unit
from hmflow.cli.common import (
    CASE_HELP,
    app,
    console,
    fail,
    folder,
    load_case,
    num,
    parse_sets,
    print_problems,
    print_tables,
)
from hmflow.console import STATUS_WORDS


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
    # reading a deck imports pandas: keeps `hmflow --help` fast
    from hmcore.model.case_init import starting_case, write_starting_case

    if summary is not None and observed is not None:
        fail("give --summary or --observed, not both")
    case_name = name or re.sub(r"[^A-Za-z0-9_.-]+", "_", deck.stem.lower())
    out = out or Path(f"{case_name}.toml")
    try:
        start = starting_case(deck, case_name, observed, summary)
        case_path, observed_path = write_starting_case(start, out, observed)
    except CaseError as exc:
        print_problems(f"Cannot start a case from {deck}", exc.problems)
        raise typer.Exit(2)
    except FileExistsError as exc:
        fail(str(exc))
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
    console.print(case_noise_text(load_case(str(case_path))), highlight=False, markup=False)
    console.print(f"next: hmflow check --case {case_path}")


@app.command()
def check(case: str = typer.Option("synthetic", "--case", help=CASE_HELP)) -> None:
    """Validate the case (deck, history, parameters); runs no simulation."""
    c = load_case(case)
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
                  f"tolerance {c.time_tolerance_days:g} d, misfit {c.misfit.variant}, "
                  f"objective {c.misfit.objective} (what a campaign minimises and selects by)")
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
    if c.fields:
        console.print("\n".join(field_lines(c.fields, c.ensemble, c.latent)), highlight=False,
                      markup=False)
    console.print(case_noise_text(c), highlight=False, markup=False)


def field_lines(fields, ensemble, latent=None) -> list[str]:
    """``check``'s lines for a case's field parameters (keyword, prior, zones, bounds), its
    ``[ensemble]`` settings and its ``[latent]`` section."""
    lines = []
    for f in fields:
        low, high = f.bounds
        copies = f", copies {', '.join(f.copies)}" if f.copies else ""
        lines.append(f"  field     {f.name:<12} {f.keyword:<6} prior {f.prior.source:<14} "
                     f"[{low:g}, {high:g}] in {'log10' if f.in_log else 'linear'} space"
                     f"{copies} {f.description}".rstrip())
        lines += [f"              {line}" for line in _prior_lines(f)]
    e = ensemble
    localisation = e.localisation + (f" (radius {e.radius:g})" if e.radius is not None else "") \
        + (f" [{e.chosen}]" if e.chosen else "")
    lines.append(f"  ensemble  {e.size} members, weights {', '.join(f'{w:g}' for w in e.weights)}"
                 f" (inflation {', '.join(f'{a:.3g}' for a in e.alphas)}), at least {e.minimum} "
                 f"must run, localisation {localisation}, seed {e.seed}")
    if latent is None:
        lines.append("  note      the fields are for the ensemble smoother (docs/ensembles.md); "
                     "`hmflow run`, `bench` and `diagnose` calibrate the scalar parameters "
                     "only (a [latent] section lets `hmflow run` move the fields)")
        return lines
    cap = f", at most {latent.max_modes}" if latent.max_modes else ""
    lines.append(f"  latent    `hmflow run` moves the fields by the leading modes of the "
                 f"{ensemble.size}-member prior (seed {ensemble.seed}) holding "
                 f"{latent.share:.0%} of its variance{cap}; coefficients in "
                 f"[-{latent.bound:g}, {latent.bound:g}], prior {latent.prior} "
                 "(docs/ensembles.md, \"Latent actions\")")
    return lines


def _prior_lines(f) -> list[str]:
    """The prior of field ``f``: its seed and zones, relation, or folder."""
    prior = f.prior
    if prior.source == "files":
        return [f"files {prior.pattern} in {prior.folder}, keyword {prior.keyword or f.keyword}"]
    if prior.source == "relation":
        return [f"u = {prior.intercept:g} + {prior.slope:g} * u({prior.from_}) + scatter "
                f"{prior.scatter:g} (u in update space), seed {prior.seed}"]
    head = (f"correlation {prior.correlation:g} with {prior.from_}'s normal score, "
            if prior.source == "cosimulation" else "")
    lines = [f"{head}seed {prior.seed}"]
    for z in prior.zones:
        variogram = getattr(prior, "variogram_of", lambda _: None)(z)
        lines.append(f"zone {z.label()}: mean {z.mean:g}, sd {z.std:g}"
                     + (f", {_variogram(variogram)}" if variogram is not None else ""))
    return lines


def _variogram(v) -> str:
    major, minor, vertical = v.ranges
    lo, hi = v.azimuth_range
    return (f"{v.model}{f' nu {v.nu:g}' if v.model == 'matern' else ''} ranges "
            f"{major:g}/{minor:g}/{vertical:g}, azimuth {lo:g}" + (f"-{hi:g}" if hi > lo else ""))


@app.command()
def evaluate(case: str = typer.Option("synthetic", "--case", help=CASE_HELP),
             set_: list[str] = typer.Option([], "--set", help="NAME=VALUE (repeatable); "
                                             "unset parameters keep the deck's values"),
             out: Path = typer.Option(..., "--out", help="Output directory (must not exist or be empty)"),
             simulator: Optional[str] = typer.Option(None, "--simulator", help="'opm' or a command "
                                                     "template like 'flow {deck} --output-dir={run_dir}'")) -> None:
    """Run one simulation and score it: writes OUT/metrics.json and OUT/responses.parquet."""
    # scoring and reporting import pandas: keeps `hmflow --help` fast
    from hmcore.model.validation import simulator_problems
    from hmcore.reporting.report import metrics_document
    from hmcore.scoring import evaluation

    c = load_case(case)
    if simulator:
        bad = simulator_problems(simulator, "--simulator")
        if bad:
            print_problems(f"--simulator {simulator!r} cannot run", bad)
            raise typer.Exit(2)
    values = parse_sets(set_, c.space.names)
    if c.fields:
        console.print("[yellow]note[/]: the field parameters ("
                      + ", ".join(f.name for f in c.fields) + ") keep the deck's values "
                      "(evaluate applies scalar parameters only)", highlight=False)
    bounds = c.space.check_in_bounds(values)
    if bounds:
        console.print(f"[yellow]note[/]: {'; '.join(bounds)} (evaluated anyway)")
    out = folder("--out", out)
    if out.exists() and any(out.iterdir()):
        fail(f"{out} exists and is not empty; hmflow never overwrites results (choose a new "
             "--out)")
    out.mkdir(parents=True, exist_ok=True)
    sim = (simulators.make_simulator(simulator, c.simulator.timeout_s, c.simulator.threads,
                                     processes=c.simulator.processes) if simulator
           else evaluation.simulator_for(c))
    ev = evaluation.evaluate(c, values, out / "run", sim)
    (out / "metrics.json").write_text(json.dumps(metrics_document(ev), indent=2))
    if ev.responses is not None:
        ev.responses.to_parquet(out / "responses.parquet", index=False)
    console.print(evaluation_text(ev, likelihood(c, ev), c.misfit.objective), highlight=False)
    if ev.reason:
        console.print(f"reason: {escape(ev.reason)}", highlight=False)
    if ev.metrics:
        print_tables(ev.metrics)
    written = [out / "metrics.json"] + ([out / "responses.parquet"] if ev.responses is not None else [])
    for path in written:  # a path on a line of its own, never wrapped
        console.print(f"wrote {path}", soft_wrap=True, highlight=False)
    if ev.status.value == "FAIL":
        raise typer.Exit(1)


def evaluation_text(ev, lk: float | None, objective: str) -> str:
    """One call in the report's words: valid, penalised or failed; E, the likelihood
    (chi2/n) and which of the two is the case's objective; the held-back E, the physics
    penalty, the history's records matched in time and the simulator's time."""
    state = dict(STATUS_WORDS).get(ev.status.value, ev.status.value)
    if ev.status.value == "FAIL":
        return f"[bold]{state}[/]: no E (simulator {ev.sim_time_s:.1f} s)"
    mark = " (the case's objective)"
    parts = [f"E = {num(ev.E, 6)}" + (mark if objective == "E" else "")]
    if lk is not None:
        parts.append(f"likelihood (chi2/n) = {num(lk, 6)}" + (mark if objective == "likelihood"
                                                             else ""))
    if math.isfinite(ev.E_heldout):
        parts.append(f"held-back E = {num(ev.E_heldout, 6)}")
    if ev.penalty > 0:
        parts.append(f"physics penalty {num(ev.penalty)}")
    parts.append(f"{100 * ev.coverage:.1f} % of the history's records matched in time")
    return f"[bold]{state}[/]: " + ", ".join(parts) + f"; simulator {ev.sim_time_s:.1f} s"


def likelihood(case, ev) -> float | None:
    """The likelihood (chi2/n) of a scored call under the noise of the case's history, as a
    campaign scores its calls before any refinement of that noise (None for a failed call)."""
    if ev.responses is None or ev.status.value == "FAIL":
        return None
    # the objective and the observation set import pandas: keeps `hmflow --help` fast
    from hmcore.calibration.objective import Objective
    from hmcore.scoring.observations import ObservationSet

    obs = ObservationSet.from_case(case)
    record = {"status": ev.status.value, "E": ev.E,
              "simulated": obs.simulated(ev.responses).tolist()}
    value = Objective("likelihood", obs).likelihood(record)
    return value if math.isfinite(value) else None
