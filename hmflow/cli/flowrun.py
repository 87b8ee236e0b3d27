"""Starting a Prefect flow from the terminal: the flow's input rules checked before Prefect
starts (:func:`flows.inputs.input_problems`, spelled as options), the workers a machine can
run, the one process per name in the store (:func:`hold_name`), the command's Prefect API (a
temporary server that dies with hmflow), what a flow that refused its input raises, and the
progress bar's columns.
"""

from __future__ import annotations

import atexit
import errno
import os
from pathlib import Path
from typing import Optional

from rich.markup import escape
from rich.progress import (
    BarColumn,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from flows.inputs import input_problems
from hmflow.cli.common import console, fail, option, refuse
from hmflow.server import temporary_api


def check_inputs(agent: Optional[str] = None, budget: Optional[int] = None,
                 workers: Optional[int] = None, task_runner: Optional[str] = None) -> None:
    """Exit 2 with every rule the options break, the rules the flow itself checks."""
    refuse(input_problems(agent, budget, workers, task_runner, spell=option))


def dask_problems(task_runner: str, dask_address: Optional[str]) -> list[str]:
    """``--dask-address`` without ``--task-runner dask`` would be ignored: a mistake."""
    return ["--dask-address needs --task-runner dask"] if dask_address and \
        task_runner != "dask" else []


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


STORAGE_ERRNOS = {errno.ENOSPC: "no space left", errno.EDQUOT: "disk quota exceeded",
                  errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
                  errno.EPERM: "operation not permitted",
                  errno.ENOENT: "a folder of the store was removed"}
"""The file system faults a command reports as one line (:func:`storage_fault`)."""


def is_storage_fault(exc: BaseException) -> bool:
    """Whether ``exc`` is a file system fault of the store (:data:`STORAGE_ERRNOS`)."""
    return isinstance(exc, OSError) and exc.errno in STORAGE_ERRNOS


def storage_fault(exc: OSError, storage: Path) -> str:
    """One line for a file system fault while writing the store: what, the path, the fix. The
    journal's records and the store's versions are written atomically, so what was finished is
    kept and the same command resumes."""
    path = exc.filename or storage
    what = STORAGE_ERRNOS.get(exc.errno, exc.strerror or str(exc))
    fixes = {errno.ENOSPC: "free space", errno.EDQUOT: "free space (or raise the quota)",
             errno.EROFS: "make the store writable (or give --storage on a writable disk)",
             errno.EACCES: "make the store writable for this user (or give another --storage)",
             errno.EPERM: "make the store writable for this user (or give another --storage)",
             errno.ENOENT: f"check that {storage} is there (restore or recreate it)"}
    fix = fixes.get(exc.errno, "repair the store")
    return (f"storage fault: {what} at {path}: {fix} and run the same command again: it "
            f"resumes (finished calls are kept)")


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


def flow_refused() -> type[Exception]:
    """What calling a flow that refused its input (a Failed state) raises; imported when an
    exception is being matched, so the CLI starts without Prefect."""
    # Prefect reads its settings on import: only after start_api
    from prefect.exceptions import FailedRun

    return FailedRun


def progress_columns(kind: str) -> list:
    """The progress bar's columns: ``run`` (calls of the budget, best E), ``bench`` (calls of
    methods x seeds x budget, the method and seed running), ``diagnose`` (simulations of the
    budget) and ``diagnose-open`` (no budget: a spinner with the count)."""
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
