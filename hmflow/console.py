"""The terminal of the ``hmflow`` command line.

* :func:`prefect_environment`: Prefect's settings for a terminal that reads well - no usage
  telemetry (an offline machine would print an ERROR about it every time), and Prefect's own
  log lines in the terminal only from WARNING up unless ``--verbose``. Values the user already
  set in the environment win.
* :class:`Watch`: a progress display driven by a thread that polls files (a campaign's journal,
  a benchmark's journals, a diagnosis's run directories); it never fails the command.
  While it is shown, Prefect's console log lines go through the same rich Console, so that a
  log line is printed above the bar instead of through it.
* :func:`summary_table`: the end-of-campaign table (the best call's E, the paper's three headline numbers,
  failed and penalised calls, where the report is).

Calls are numbered from 1 wherever they are shown (journal records store ``index`` from 0).
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import Progress
from rich.table import Table

CONSOLE_LEVEL_VAR = "PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL"
"""Level of Prefect's console handler (the terminal) only: the flow and task run logs still
reach a Prefect server (the UI) at the loggers' level (PREFECT_LOGGING_LEVEL, default INFO)."""
QUIET_LEVEL = "WARNING"
_USER_LEVEL_VARS = ("PREFECT_LOGGING_LEVEL", CONSOLE_LEVEL_VAR)
_quieted = False  # CONSOLE_LEVEL_VAR holds hmflow's own default (not the user's value)


def prefect_environment(verbose: bool = False) -> None:
    """Set Prefect's environment for the terminal; call before Prefect is imported (it reads its
    settings once, on import; a console handler already configured is adjusted as well).

    * ``PREFECT_SERVER_ANALYTICS_ENABLED=false``: the temporary Prefect server hmflow starts
      otherwise sends a usage heartbeat, and on a machine without internet prints
      ``ERROR | prefect.server.services.telemetry - Failed to send telemetry``.
    * ``DO_NOT_TRACK=1``: the Prefect SDK's own usage events (and its first-run notice in an
      interactive terminal) are off too.
    * ``PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS=120``: Prefect waits 20 s for its
      temporary server by default; on 2 cores busy with simulations its start takes longer.
    * ``PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL=WARNING`` unless ``verbose``: Prefect's INFO lines
      (temporary server, flow and task runs) stay out of the terminal and the progress bar.

    Each is a default: a value the user set in the environment is left as it is (for the log
    level: PREFECT_LOGGING_LEVEL or PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL). ``verbose`` undoes
    hmflow's own quiet default only."""
    global _quieted
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
    if verbose:
        if _quieted:
            if os.environ.get(CONSOLE_LEVEL_VAR) == QUIET_LEVEL:
                del os.environ[CONSOLE_LEVEL_VAR]
            _quieted = False
            _set_console_handler_level(logging.NOTSET)  # logging.yml's default: all that comes
    elif not _quieted and not any(os.environ.get(k) for k in _USER_LEVEL_VARS):
        os.environ[CONSOLE_LEVEL_VAR] = QUIET_LEVEL
        _quieted = True
        _set_console_handler_level(logging.WARNING)


def _prefect_console_handlers() -> list[logging.Handler]:
    """Prefect's console handlers already configured in this process (none before Prefect is
    imported)."""
    mod = sys.modules.get("prefect.logging.handlers")
    cls = getattr(mod, "PrefectConsoleHandler", None)
    if cls is None:
        return []
    loggers = [logging.getLogger()] + [lg for lg in list(logging.Logger.manager.loggerDict.values())
                                       if isinstance(lg, logging.Logger)]
    found: list[logging.Handler] = []
    for lg in loggers:
        for h in lg.handlers:
            if isinstance(h, cls) and h not in found:
                found.append(h)
    return found


def quiet_prefect_lines(line_filter: logging.Filter) -> None:
    """Add ``line_filter`` to Prefect's console handlers (the terminal only: the records still
    reach the Prefect server); call it once Prefect is imported."""
    for h in _prefect_console_handlers():
        if line_filter not in h.filters:
            h.addFilter(line_filter)


def _set_console_handler_level(level: int) -> None:
    for h in _prefect_console_handlers():
        h.setLevel(level)


class _Forward:
    """Stands in for a Prefect console handler's own rich Console: its lines are printed by
    ours, as plain text (a log message is no rich markup)."""

    def __init__(self, console: Console):
        self.console = console

    def print(self, message: Any, *args, **kwargs) -> None:
        self.console.print(message, soft_wrap=True, markup=False, highlight=False, emoji=False)


class Watch:
    """A rich progress display in a thread that calls ``poll()`` every ``interval`` seconds (and
    once more when the ``with`` block ends, so that the display ends on the final count).

    ``poll`` returns the task's ``completed`` (and optionally ``total``) plus the fields the
    ``columns`` show (``initial`` gives their first values). A failing ``poll`` (files not
    there yet, a record being replaced) is ignored until the next one; a failing display never
    fails the command. While the display runs, Prefect's console log lines are printed by the
    same ``console`` (above the bar, never through it)."""

    def __init__(self, console: Console, poll: Callable[[], dict], columns: list,
                 total: int | None = None, initial: dict | None = None,
                 interval: float = 1.0):
        self.console, self.poll, self.columns = console, poll, columns
        self.total, self.initial, self.interval = total, dict(initial or {}), interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hmflow-progress", daemon=True)
        self._saved: list[tuple[logging.Handler, Any]] = []

    def __enter__(self) -> Watch:
        for h in _prefect_console_handlers():
            self._saved.append((h, getattr(h, "console", None)))
            h.console = _Forward(self.console)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> bool:
        self._stop.set()
        self._thread.join()
        for h, original in self._saved:
            if original is not None:
                h.console = original
        self._saved.clear()
        return False

    def _run(self) -> None:
        try:
            with Progress(*self.columns, console=self.console, transient=False) as bar:
                task = bar.add_task("", total=self.total, **self.initial)
                while True:
                    finished = self._stop.is_set()
                    try:
                        state = self.poll() or {}
                    except Exception:  # noqa: BLE001 - the next poll tries again
                        state = {}
                    if state:
                        bar.update(task, **state)
                    if finished:
                        break
                    self._stop.wait(self.interval)
        except Exception:  # noqa: BLE001 - a progress display never fails the command
            pass


# ================================================================================== polls
def campaign_poll(storage: Path, campaign: str, budget: int) -> Callable[[], dict]:
    """Calls journaled of ``budget`` and the best valid E so far."""

    def poll() -> dict:
        # storage imports pandas: keeps `hmflow --help` fast
        from storage import ArtifactStore, EvaluationJournal

        if not (Path(storage) / campaign / "evaluations").is_dir():
            return {}
        rows = EvaluationJournal(ArtifactStore(storage), campaign).rows()
        ok = [r["E"] for r in rows if r.get("status") == "COMPLETE" and r.get("E") is not None]
        return {"completed": min(len(rows), budget), "best": f"{min(ok):.5g}" if ok else "-"}

    return poll


def bench_poll(storage: Path, campaigns: dict[str, tuple[str, int]], budget: int,
               workers: int | None = None, bench: str | None = None) -> Callable[[], dict]:
    """Calls journaled over all the benchmark's campaigns (each counted up to ``budget``) and
    the method and seed running: the first campaign, in the benchmark's order, not done.
    Given ``workers`` (and ``bench``), calls stored under other settings are not counted: a
    resume that the flow will refuse shows them as not done, never as a full bar."""

    def poll() -> dict:
        # Prefect (via flows) and pandas (storage): polled only once the flow runs
        from flows.bench import same_bench, same_settings
        from storage import ArtifactStore, EvaluationJournal

        if bench is not None and workers is not None and same_bench(
                storage, bench, budget, workers) is False:
            return {"completed": 0, "current": f"{bench} was stored with another budget or "
                                               "worker count"}
        store = ArtifactStore(storage)
        done, current, started = 0, None, False
        for name, (method, seed) in campaigns.items():
            n = 0
            if (Path(storage) / name).is_dir():
                started = True
                if workers is None or same_settings(storage, name, method, seed,
                                                    workers) is not False:
                    n = min(len(EvaluationJournal(store, name).indices()), budget)
            done += n
            if current is None and n < budget:
                current = f"{method} seed {seed}"
        if not started:
            current = "reference runs"
        return {"completed": done, "current": current or "every method and seed done"}

    return poll


_RUN_DIR_RE = re.compile(r"(?P<step>.+)-(?P<n>\d+)(\.\d+)?")


def diagnosis_poll(storage: Path, campaign: str) -> Callable[[], dict]:
    """Simulations of the diagnosis: its run directories
    (``<storage>/<campaign>/diagnosis-runs/<step>-<n>``) made since the poll was created, and the
    step of the newest. A directory is made as its simulation starts, so the count runs up to
    ``workers`` ahead of the finished simulations."""
    root = Path(storage) / campaign / "diagnosis-runs"
    try:
        before = set(os.listdir(root))
    except OSError:
        before = set()

    def poll() -> dict:
        try:
            new = set(os.listdir(root)) - before
        except OSError:
            return {}
        newest = max((m for m in map(_RUN_DIR_RE.fullmatch, new) if m),
                     key=lambda m: int(m["n"]), default=None)
        return {"completed": len(new), "step": newest["step"] if newest else "-"}

    return poll


# ================================================================================ summary
STATUS_WORDS = (("COMPLETE", "valid"), ("INVALID", "penalised"), ("FAIL", "failed"))


def status_text(counts: dict | None) -> str:
    """``{'COMPLETE': 3, 'INVALID': 1}`` -> '3 valid, 1 penalised'."""
    counts = dict(counts or {})
    parts = [f"{counts.pop(k)} {word}" for k, word in STATUS_WORDS if counts.get(k)]
    parts += [f"{v} {k}" for k, v in sorted(counts.items()) if v]
    return ", ".join(parts) or "none"


def _fmt(v: Any, digits: int) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{float(v):.{digits}f}"


def summary_table(doc: dict, report: str | Path | None, title: str = "Summary") -> Table:
    """The end-of-campaign table from a stored ``report.json``: campaign, the best call's E (N of M,
    calls numbered from 1), the best case's macro NMSE, R^2 and C_match (the paper's rounding),
    calls failed / penalised, and ``report`` (the path of the report)."""
    calls = int(doc.get("calls") or 0)
    best = doc.get("best") or None
    counts = doc.get("status_counts") or {}
    t = Table(title=title, show_header=False, title_justify="left")
    t.add_column("item", style="bold", no_wrap=True)
    t.add_column("value", overflow="fold")
    t.add_row("campaign", str(doc.get("campaign", "")))
    if best and best.get("E") is not None:
        t.add_row("E of the best call", f"{best['E']:.6g} (call {int(best['index']) + 1} of "
                  f"{calls})")
    elif calls:
        t.add_row("E of the best call", f"none: no valid call of {calls}")
    else:
        t.add_row("E of the best call", "no calibration calls under this name")
    if best:  # the paper's three headline numbers of the best case (fitted history)
        macro = best.get("macro") or {}
        t.add_row("macro NMSE", _fmt(macro.get("nmse"), 4))
        t.add_row("macro R²", _fmt(macro.get("r2"), 4))
        cm = _fmt(macro.get("cmatch"), 2)
        t.add_row("C_match", cm + (" %" if cm != "n/a" else ""))
    if calls:
        t.add_row("failed / penalised", f"{counts.get('FAIL', 0)} failed, "
                                        f"{counts.get('INVALID', 0)} penalised (of {calls} calls)")
    if report:
        t.add_row("report", str(report))
    return t
