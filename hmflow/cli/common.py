"""The Typer app of the ``hmflow`` command line and what its commands share: the help texts of
common options, ``--help`` in plain words at any width (:class:`PlainHelp`), the command start
(Prefect's terminal settings, SIGTERM), turning bad input into exit 2 with every problem on
stderr (the user's text printed as it is), and printing that reads at 80 columns and in a pipe
(paths never broken, table columns wrapped instead of cut).

Importing this module changes nothing in the process: Prefect's environment is set when a
command runs (:func:`_start`), and the modules of hmcore that import pandas or Prefect are
imported by the commands that use them, so that ``hmflow --help`` starts fast.
"""

from __future__ import annotations

import difflib
import inspect
import math
import re
import signal
from collections.abc import Iterable
from pathlib import Path
from typing import NoReturn, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table
from typer.core import TyperGroup, TyperOption

from hmcore.errors import CaseError
from hmflow.console import prefect_environment

VALUE_WORDS = {"str": "TEXT", "int": "INTEGER", "float": "NUMBER"}
"""What ``--help`` shows after an option that takes a value, for typer's ``<str>``,
``<int range>``, ``<list[float]>``...; other kinds spelled in capitals (``<path>``: PATH)."""


class PlainHelp(TyperGroup):
    """The command group, whose ``--help`` (its own and every command's) reads in plain words
    at any width: a flag shows no value (typer shows ``<bool>``), an option its value as a
    word (TEXT, INTEGER, NUMBER, PATH), and a command's text as paragraphs rewrapped to the
    terminal (typer keeps the docstring's line breaks after the first paragraph, ragged at 80
    columns)."""

    def get_command(self, ctx, cmd_name):
        command = super().get_command(ctx, cmd_name)
        if command is not None:
            command.help = plain_paragraphs(command.help)
            for param in command.get_params(ctx):  # (the --help option made on first call)
                plain_value(param, ctx)
        return command

    def get_params(self, ctx):
        params = super().get_params(ctx)
        for param in params:
            plain_value(param, ctx)
        return params


def plain_value(param, ctx) -> None:
    """Set an option's metavar, which ``--help`` shows after it, to a plain word (none for a
    flag); an option that names its own is left alone."""
    if not isinstance(param, TyperOption) or param.metavar is not None:
        return
    if param.is_flag or param.count:
        param.metavar = ""
        return
    kind = param.display_type(ctx).strip("<>")
    kind = re.sub(r"^list\[(.*)\]$", r"\1", kind).removesuffix(" range")
    param.metavar = kind if "|" in kind else VALUE_WORDS.get(kind, kind.upper())


def plain_paragraphs(text: str | None) -> str | None:
    """A docstring as paragraphs of one line each (what follows a form feed, typer's end of
    the help, left out), for the terminal to wrap at its width."""
    if not text:
        return text
    shown = inspect.cleandoc(text).partition("\f")[0]
    return "\n\n".join(" ".join(p.split()) for p in shown.split("\n\n"))


app = typer.Typer(cls=PlainHelp, add_completion=False, no_args_is_help=True,
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
KINDS_HELP = ("Families of candidate extensions to search, comma-separated (default all but "
              "the last two): "
              "well_skin, regional_permeability, layer_permeability, vertical_permeability, "
              "aquifer_strength, fault_transmissibility, relative_permeability, "
              "productivity_change, contact_depth, solution_gas")
"""Spelled out so that ``--help`` does not import the diagnosis; a test holds it to
:data:`hmcore.diagnosis.candidate.KINDS`, as ``GENERATORS_HELP`` to the generators."""
GENERATORS_HELP = ("partial_fault, offcentre_region, relperm_endpoint, relperm_scaling, "
                   "two_kinds, contact, pvt, dated_productivity, late_productivity, "
                   "permeability_trend, completion_change")
DEFAULT_STORAGE = Path("./hmflow-storage")


@app.callback()
def _start() -> None:
    """Runs before every command (never on import):

    * Prefect's terminal defaults, before Prefect is imported (every command imports it late):
      no usage telemetry (no ERROR about it on a machine without internet), Prefect's own log
      lines in the terminal from WARNING up (``--verbose``: all); a user's own settings win -
      see :func:`hmflow.console.prefect_environment`.
    * SIGTERM (``kill PID``, a batch system's time limit) stops hmflow as Ctrl-C does: the
      flow run ends as cancelled, the temporary Prefect server is stopped, and the journal
      keeps every finished call (the same command resumes). Without this, SIGTERM ended the
      process at once and left the temporary server running."""
    prefect_environment()

    def interrupt(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, interrupt)


def main() -> None:  # pragma: no cover - console entry
    app()


# ------------------------------------------------------------------------------ bad input
def refuse(problems: Iterable[str], soft_wrap: bool = False) -> None:
    """Exit 2 with one line per problem on stderr when there is any; return when none."""
    problems = list(problems)
    for p in problems:
        _say(p, soft_wrap)
    if problems:
        raise typer.Exit(2)


def fail(problem: str, soft_wrap: bool = False) -> NoReturn:
    """Exit 2 with one line on stderr."""
    _say(problem, soft_wrap)
    raise typer.Exit(2)


def _say(problem: str, soft_wrap: bool) -> None:
    err_console.print(f"[red]x[/] {escape(str(problem))}", highlight=False, soft_wrap=soft_wrap)


def print_problems(title: str, problems) -> None:
    """Every problem on stderr: where, what, fix (the user's text printed as it is, never read
    as rich markup: '[[parameters]]' stays)."""
    err_console.print(f"[bold red]{escape(title)}[/] - {len(problems)} problem(s):")
    for p in problems:
        err_console.print(f"  [red]x[/] {escape(p.where)}\n      {escape(p.what)}"
                          + (f"\n      fix: {escape(p.fix)}" if p.fix else ""), highlight=False)


def option(name: str) -> str:
    """A flow parameter spelled as the command line's option: ``task_runner`` ->
    ``--task-runner``."""
    return "--" + name.replace("_", "-")


def checked_campaign(value: Optional[str]) -> Optional[str]:
    """A campaign name given on the command line: refused at once (exit 2, the rule stated)
    when it is empty or could leave the store (``''``, ``../S``, ``a/b``)."""
    if value is None:
        return value
    # storage imports pandas: keeps `hmflow --help` fast
    from storage import validate_name

    try:
        return validate_name("campaign", value)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None


SHOWN_CAMPAIGNS = 12
"""At most this many campaign names in the line saying a name is not in the store."""


def no_campaign(campaign: str, storage: Path) -> str:
    """One line: ``campaign`` is not in the store, the stored name nearest to it (a
    did-you-mean) and the campaigns the store holds."""
    names = stored_campaigns(storage)
    if not names:
        held = "it does not exist" if not storage.is_dir() else "it holds no campaign"
        return f"no campaign '{campaign}' in {storage}: {held} (give --storage DIR)"
    near = difflib.get_close_matches(campaign, names, n=1, cutoff=0.6)
    hint = f" Did you mean '{near[0]}'?" if near else ""
    more = len(names) - SHOWN_CAMPAIGNS
    shown = ", ".join(names[:SHOWN_CAMPAIGNS]) + (f" and {more} more" if more > 0 else "")
    return f"no campaign '{campaign}' in {storage}.{hint} It holds: {shown}"


def stored_campaigns(storage: Path) -> list[str]:
    """The campaigns in a store, sorted: its folders but the reference runs' (the folder a
    campaign's ``campaign.json`` names as its ``reference``)."""
    # storage imports pandas: keeps `hmflow --help` fast
    from storage import ArtifactStore

    if not storage.is_dir():
        return []
    store = ArtifactStore(storage)
    names = store.campaigns()
    references = set()
    for name in names:
        try:
            references.add((store.settings(name) or {}).get("reference"))
        except (OSError, ValueError):  # an unreadable campaign.json: still a folder
            continue
    return [n for n in names if n not in references]


def folder(option_name: str, path: Path) -> Path:
    """A folder option (``--out``, ``--storage``): exit 2 with one line when it names a file
    or cannot be a path, before anything runs."""
    try:
        path = path.expanduser()
    except RuntimeError as exc:  # ~nosuchuser
        fail(f"{option_name} {path}: {exc}")
    if path.exists() and not path.is_dir():
        fail(f"{option_name} {path} is a file, not a folder; give a folder (it is created "
             "when missing)")
    if any(p.exists() and not p.is_dir() for p in path.parents):
        fail(f"{option_name} {path}: a part of the path is a file, not a folder")
    return path


def load_case(case: str):
    """The case ``case`` names (a TOML file or 'synthetic'); exit 2 with every problem."""
    # hmcore.cases imports pandas: keeps `hmflow --help` fast
    from hmcore.cases import load_case as load

    try:
        return load(case)
    except CaseError as exc:
        print_problems(f"Case {case} is not valid", exc.problems)
        raise typer.Exit(2)


def parse_sets(sets: list[str], names: list[str]) -> dict[str, float]:
    """``--set NAME=VALUE`` items as values of the parameters ``names``; exit 2 with every
    item that is no known name or no finite number."""
    values = {}
    problems = []
    for item in sets:
        name, sep, val = item.partition("=")
        if not sep:
            problems.append(f"--set {item!r}: expected NAME=VALUE")
            continue
        if name not in names:
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
    refuse(problems)
    return values


# ------------------------------------------------------------------------------ printing
def num(v, digits=4) -> str:
    """A number as the terminal shows it ('n/a' for none or not finite)."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.{digits}f}"


TEXT_COLUMNS = ("category", "ratio", "well", "why")
"""The tables' columns of words (left-aligned); the others hold numbers."""


def print_tables(metrics: dict, title: str = "") -> None:
    """Print the paper's three tables (categories; C_match per well; GOR / water cut per well),
    in the paper's rounding. Nothing is cut at any width: words wrap at spaces (the reasons
    a record is left out, ``shut_in_observed``, are spelled with spaces), a longer word folds
    onto the next line, and the per-well table leaves out a column with no record at any well,
    saying so."""
    # the reporting imports pandas: keeps `hmflow --help` fast
    from hmcore.reporting.paper_tables import paper_tables

    heads = {"categories": "match by category", "wells": "C_match (%) per well and category",
             "ratios": "GOR and water cut per well (records used, left out and why)"}
    for key, df in paper_tables(metrics).items():
        empty = [c for c in df.columns if c not in TEXT_COLUMNS and df[c].isna().all()]
        if key != "wells":
            empty = []
        console.print(text_table(f"{title} {heads[key]}".strip(), df.drop(columns=empty)))
        if empty:
            console.print(f"({', '.join(map(str, empty))}: no record at any well, left out)",
                          highlight=False)


def text_table(title: str, df) -> Table:
    """A table of ``df`` whose cells are never cut (``overflow='fold'``, no ellipsis)."""
    from hmcore.reporting.paper_tables import cell  # pandas, as above

    t = Table(title=title)
    for col in df.columns:
        t.add_column(str(col), justify="left" if col in TEXT_COLUMNS else "right",
                     overflow="fold")
    for row in df.itertuples(index=False):
        t.add_row(*[cell(c, v).replace("_", " ") if c == "why" else cell(c, v)
                    for c, v in zip(df.columns, row)])
    return t


def print_forecast(storage: Path, campaign: str) -> None:
    """The stored forecast: P90/P50/P10 of each quantity, prior and posterior, and the data
    misfit (mean square whitened residual) of each round of runs."""
    # storage imports pandas: keeps `hmflow --help` fast
    from storage import ArtifactStore
    from storage.ensemble import FORECAST_STEP

    version = ArtifactStore(storage).latest(campaign, FORECAST_STEP)
    table = version.read_parquet("forecast.parquet")
    doc = version.read_json("summary.json")
    t = Table(title="Forecast at the schedule's end (P90 low, P10 high)")
    for col in ("quantity", "ensemble", "members", "P90", "P50", "P10"):
        t.add_column(col, justify="left" if col in ("quantity", "ensemble") else "right",
                     overflow="fold")  # never cut (see text_table)
    for row in table.sort_values(["well", "quantity"], kind="stable").itertuples():
        t.add_row(row.label, row.ensemble, str(row.members),
                  *(f"{getattr(row, p):.5g}" for p in ("P90", "P50", "P10")))
    console.print(t)
    for it in doc["iterations"]:
        failed = (f", {it['failed']} failed {it['failed_by_kind']}" if it["failed"] else "")
        misfit = it["misfit_median"]
        console.print(f"ensemble {it['iteration']}: {it['ran']}/{it['planned']} members ran"
                      f"{failed}; median misfit "
                      + (f"{misfit:.4g}" if misfit is not None else "n/a"), highlight=False)
