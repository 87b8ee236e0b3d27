"""Starting a Prefect flow from the terminal: the flow's input rules checked before Prefect
starts (:func:`flows.inputs.input_problems`, spelled as options), the workers a machine can
run, the one process per name in the store (:func:`hold_name`), the command's Prefect API (a
temporary server that dies with hmflow), what a flow that refused its input raises, and the
progress bar's columns.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape
from rich.progress import (
    BarColumn,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from flows.inputs import input_problems
from hmcore.model.cluster import CLUSTER_KINDS, cluster_problems
from hmcore.model.fingerprint import deck_file_hashes
from hmflow.cli.common import console, fail, option, print_problems, refuse
from hmflow.console import quiet_prefect_lines
from hmflow.server import temporary_api


def check_inputs(agent: Optional[str] = None, budget: Optional[int] = None,
                 workers: Optional[int] = None, task_runner: Optional[str] = None) -> None:
    """Exit 2 with every rule the options break, the rules the flow itself checks."""
    refuse(input_problems(agent, budget, workers, task_runner, spell=option))


def dask_problems(task_runner: str, dask_address: Optional[str]) -> list[str]:
    """``--dask-address`` without ``--task-runner dask`` would be ignored: a mistake."""
    return ["--dask-address needs --task-runner dask"] if dask_address and \
        task_runner != "dask" else []


CLUSTER_HELP = ("Run each simulator call in a batch job of this queue system (slurm, pbs, lsf; "
                "dask-jobqueue), as the case file's cluster section says; see docs/cluster.md")


def batch_runner(cluster: Optional[str], task_runner: str, dask_address: Optional[str]) -> str:
    """The task runner ``--cluster`` stands for (its kind), else ``--task-runner``; exit 2
    with one line on an unknown kind, or when ``--cluster`` comes with another runner."""
    if cluster is None:
        return task_runner
    if cluster not in CLUSTER_KINDS:
        fail(f"--cluster must be one of {list(CLUSTER_KINDS)}, got {cluster!r}")
    if task_runner not in ("threads", cluster) or dask_address:
        fail(f"--cluster {cluster} runs the calls in {cluster} jobs: give it without "
             "--task-runner and --dask-address")
    return cluster


def check_cluster(case, task_runner: str, storage: Path) -> None:
    """For a batch system's runner: exit 2 with every problem of the case's ``[cluster]``
    against its simulator (walltime, cores; :func:`hmcore.model.cluster.cluster_problems`)
    and against the highest peak memory ``storage`` measured for runs of this deck
    (:func:`storage.peaks.measured_peak`), before any job is submitted; when none was
    measured, say that the memory is left to the batch system."""
    if task_runner not in CLUSTER_KINDS:
        return
    # storage imports pandas: keeps `hmflow --help` fast
    from storage import ArtifactStore
    from storage.peaks import measured_peak

    peak = measured_peak(ArtifactStore(storage), deck_file_hashes(case))
    problems = cluster_problems(case.cluster, case.simulator.timeout_s,
                                case.simulator.cores_per_run, str(case.source),
                                None if peak is None else peak.bytes)
    if problems:
        print_problems(f"Case {case.source} cannot run its calls in {task_runner} jobs",
                       problems)
        if peak is not None:
            console.print(f"(the peak: call {peak.index} of campaign {escape(peak.campaign)}, "
                          f"the highest of {peak.runs} measured runs of this deck in "
                          f"{escape(str(storage))})", soft_wrap=True, highlight=False)
        raise typer.Exit(2)
    if peak is None:
        console.print(f"[yellow]note[/]: no run of this deck was measured in "
                      f"{escape(str(storage))} yet: {case.cluster.memory} per job is not "
                      "checked against a run's peak memory before the jobs are submitted "
                      "(only the batch system enforces it)", soft_wrap=True, highlight=False)
    else:
        console.print(f"memory per job {case.cluster.memory}: a run of this deck peaked at "
                      f"{peak.bytes / 1e6:.0f} MB (highest of {peak.runs} measured in the "
                      "store)", highlight=False)


def fit_workers(workers: int, threads: int, task_runner: str) -> int:
    """Local runs: at most as many simulator threads at once as the machine has cores
    (``threads``: cores one run uses, its threads x MPI processes)."""
    cores = os.cpu_count() or 1
    if task_runner != "threads" or workers * threads <= cores:
        return workers
    fitted = max(1, cores // threads)
    console.print(f"[yellow]note[/]: {workers} workers x {threads} cores per run would "
                  f"need {workers * threads} cores, this machine has {cores}: {fitted} "
                  f"worker(s)")
    return fitted


def hold_name(storage: Path, name: str, kind: str) -> None:
    """Take the store's lock on ``name`` for this command (released when it ends): exit 2
    with one line naming the holder when another live process holds it (or a process on
    another host of a shared store); a lock left by a process of this host that died is taken
    over, with a warning. Call it before Prefect starts and before anything is simulated."""
    # storage imports pandas: keeps `hmflow --help` fast
    from storage.lock import NameHeldError, NameLock

    lock = NameLock(storage, name, kind)
    try:
        lock.acquire()
    except NameHeldError as exc:
        fail(str(exc), soft_wrap=True)
    except OSError as exc:
        if not is_storage_fault(exc, storage):
            raise
        fail(storage_fault(exc, storage), soft_wrap=True)
    if lock.taken_over is not None:
        console.print(f"[yellow]warning[/]: took over the lock of {escape(name)} from "
                      f"{lock.taken_over.describe()}, which no longer runs", highlight=False,
                      soft_wrap=True)
    ctx = _command_context()
    if ctx is not None:
        ctx.call_on_close(lock.release)
    else:
        atexit.register(lock.release)


def is_storage_fault(exc: BaseException, storage: Path) -> bool:
    """Whether ``exc`` is the store's file system failing (:func:`storage.space.is_fault`)."""
    # storage imports pandas: keeps `hmflow --help` fast
    from storage.space import is_fault

    return is_fault(exc, storage)


def storage_fault(exc: OSError, storage: Path) -> str:
    """One line for a file system fault of the store: what, the path, the fix. The journal's
    records and the store's versions are written atomically and a call the fault made fail is
    not journaled, so what was finished is kept and the same command resumes."""
    from storage.space import FAULTS  # pandas, as above

    fault = FAULTS.get(exc.errno)
    what = fault.what if fault else (exc.strerror or str(exc))
    fix = fault.fix if fault else "repair the store"
    return (f"storage fault: {what} at {exc.filename or storage}: {fix} and run the same "
            "command again: it resumes (finished calls are kept)")


def quiet_storage_faults(storage: Path) -> None:
    """Keep Prefect's terminal lines about a storage fault (the failed task, the flow's
    traceback) out of the terminal: the command says it in one line
    (:func:`storage_fault`). Call it once Prefect is imported; the lines still reach the
    Prefect server (the UI)."""
    quiet_prefect_lines(StorageFaultFilter(storage))


FAULT_TEXT = re.compile(r"\b(?:OSError|PermissionError|FileNotFoundError)(?::\s*\[Errno |\()(\d+)")
"""An ``OSError`` as Prefect spells it in a line (``OSError: [Errno 28] ...``,
``OSError(28, ...)``), with its errno."""


class StorageFaultFilter(logging.Filter):
    """Drops a log record about a storage fault of the store at ``storage``: one carrying the
    exception, or one whose text names such an ``OSError``."""

    def __init__(self, storage: Path):
        super().__init__()
        # storage imports pandas: keeps `hmflow --help` fast
        from storage.space import FAULTS, is_fault

        self.storage = Path(storage)
        self.anywhere = {n for n, f in FAULTS.items() if f.anywhere}
        self.inside = set(FAULTS) - self.anywhere
        self.is_fault = is_fault

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if exc is not None and self.is_fault(exc, self.storage):
            return False
        text = record.getMessage()
        found = FAULT_TEXT.search(text)
        if found is None:
            return True
        number = int(found.group(1))
        return not (number in self.anywhere
                    or (number in self.inside and str(self.storage) in text))


def start_api() -> None:
    """The command's Prefect API: the configured server, or a temporary one that dies with
    hmflow (:mod:`hmflow.server`), stopped when the command ends. Call it after the input is
    checked and before Prefect is imported (Prefect reads its settings once, on import)."""
    api = temporary_api()
    api.__enter__()  # (killed with hmflow if it dies)

    def stop() -> None:
        try:  # the run's last log lines reach the server before it stops
            from prefect.logging.handlers import APILogWorker  # Prefect: imported by then

            APILogWorker.drain_all(timeout=5)
        except Exception:  # nothing to send, or Prefect never imported
            pass
        api.__exit__(None, None, None)

    ctx = _command_context()
    if ctx is not None:  # stopped when the command ends (also when it runs in-process)
        ctx.call_on_close(stop)
    else:
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


@contextlib.contextmanager
def one_line_failures(storage: Path) -> Iterator[None]:
    """Around a flow's run: a fault of the store's file system (:func:`storage_fault`), a
    refused input (ValueError) or a flow that refused it (:func:`flow_refused`) ends the
    command in one line, exit 2; anything else goes on up."""
    try:
        yield
    except OSError as exc:
        if not is_storage_fault(exc, storage):
            raise
        fail(storage_fault(exc, storage), soft_wrap=True)
    except (ValueError, flow_refused()) as exc:
        fail(str(exc))


def flow_refused() -> type[Exception]:
    """What calling a flow that refused its input (a Failed state) raises; imported when an
    exception is being matched, so the CLI starts without Prefect."""
    # Prefect reads its settings on import: only after start_api
    from prefect.exceptions import FailedRun

    return FailedRun


def progress_columns(kind: str) -> list:
    """The progress bar's columns: ``run`` (calls of the budget, the lowest E so far),
    ``bench`` (calls of methods x seeds x budget, the method and seed running), ``diagnose``
    (simulations of the budget) and ``diagnose-open`` (no budget: a spinner with the
    count)."""
    count = TextColumn("{task.completed}/{task.total}")
    if kind == "run":
        return [TextColumn("[bold]calls"), BarColumn(), count,
                TextColumn("lowest E {task.fields[best]}"), TimeElapsedColumn(), TextColumn("ETA"),
                TimeRemainingColumn()]
    if kind == "bench":
        return [TextColumn("[bold]calls"), BarColumn(), count, TimeElapsedColumn(),
                TextColumn("ETA"), TimeRemainingColumn(), TextColumn("{task.fields[current]}")]
    if kind == "diagnose":  # the steps may stop short of the budget
        return [TextColumn("[bold]simulations (budget {task.total})"), BarColumn(), count,
                TimeElapsedColumn(), TextColumn("step {task.fields[step]}")]
    return [SpinnerColumn(), TextColumn("[bold]simulations {task.completed}"),
            TimeElapsedColumn(), TextColumn("step {task.fields[step]}")]
