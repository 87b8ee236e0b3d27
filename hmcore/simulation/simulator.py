"""Simulator adapters: run a prepared deck in an isolated directory, return the summary path.

Two real backends:

* :class:`OpmFlow` - OPM Flow through the ``opm-simulators`` Python bindings, one fresh
  subprocess per run, one thread.
* :class:`CommandLineSimulator` - any command-line simulator given a command template such as
  ``"flow {deck} --output-dir={run_dir}"`` (Debian's ``flow``, or a wrapper around Eclipse/IMEX
  that leaves an Eclipse-format summary in the run directory).

Every failure becomes a :class:`~hmcore.errors.SimulationError` with its reason, the log tail
and the run directory; nothing here retries.
"""

from __future__ import annotations

import math
import os
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from hmcore.errors import FailureKind, SimulationError

LOG_TAIL_CHARS = 4000


@dataclass(frozen=True)
class SimulationResult:
    """Where a finished run left its summary (``CASE.SMSPEC``), how long it took and its peak
    resident memory (bytes; None when not measured)."""

    summary_path: Path
    run_dir: Path
    wall_time_s: float
    backend: str
    peak_rss_bytes: int | None = None


@dataclass(frozen=True)
class Finished:
    """The leader of a process group that ended: its return code (negative: the signal that
    killed it) and the group's peak resident memory in bytes (see :func:`_wait`; 0 when it
    ended before it was first looked at)."""

    returncode: int
    peak_rss_bytes: int


class Simulator(Protocol):
    """Runs ``deck`` with all output in ``run_dir``; raises SimulationError on failure."""

    name: str

    def run(self, deck: Path, run_dir: Path) -> SimulationResult: ...


def _tail(text: str) -> str:
    return text[-LOG_TAIL_CHARS:]


def _failure_log(run_dir: Path, stderr_path: Path, stdout_path: Path) -> str:
    """What the simulator said: stderr, then error lines of stdout and of CASE.PRT/DBG files.

    OPM prints parser errors to stdout (with its chatter), Debian's flow to stdout and the PRT
    file; keeping only stderr would lose the reason.
    """
    parts = [stderr_path.read_text(errors="replace").strip()]
    out = stdout_path.read_text(errors="replace") if stdout_path.exists() else ""
    for text in [out] + [p.read_text(errors="replace") for p in sorted(run_dir.glob("*.PRT"))
                         + sorted(run_dir.glob("*.DBG"))]:
        lines = text.splitlines()
        hits = [i for i, line in enumerate(lines) if "error" in line.lower()]
        if hits:
            parts.append("\n".join(lines[max(0, hits[0] - 2): hits[0] + 12]))
        elif text.strip():
            parts.append("\n".join(lines[-5:]))
    return _tail("\n".join(p for p in parts if p))


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: SIGKILL this process when the thread that started it dies (the campaign)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def run_in_own_group(cmd: list[str], stdout, stderr, timeout_s: float, cwd: Path
                     ) -> Finished:
    """Run ``cmd`` as the leader of its own process group, killed with the process that
    started it; on timeout the whole group (the simulator and anything it started: an MPI
    launcher's ranks, a wrapper script's child) is killed, then TimeoutExpired is raised."""
    proc = subprocess.Popen(cmd, stdout=stdout, stderr=stderr, cwd=cwd, start_new_session=True,
                            preexec_fn=_die_with_parent if sys.platform == "linux" else None)
    try:
        finished = _wait(proc, timeout_s)
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        raise
    except BaseException:  # interrupted (Ctrl-C, SIGTERM): leave nothing behind
        _kill_group(proc)
        raise
    finally:
        _kill_group(proc, after_exit=True)
    return finished


WAIT_POLL_MAX_S = 0.05
"""The longest pause between two looks at a running simulator."""
GROUP_SCAN_S = 1.0
"""How often the other members of the group (an MPI launcher's ranks, a wrapper's child) are
looked for in /proc."""


def _wait(proc: subprocess.Popen, timeout_s: float) -> Finished:
    """Wait for ``proc`` (every millisecond at first, then at most every
    :data:`WAIT_POLL_MAX_S`), TimeoutExpired after ``timeout_s``; meanwhile read the high-water
    mark of resident memory (``VmHWM`` in /proc/PID/status: since the process's exec, not the
    forked copy of this process it began as) of the leader at each look and of the group's
    other members every :data:`GROUP_SCAN_S`. The peak is the largest sum seen over the
    members (each at its own high-water mark: an upper bound of what they held at once)."""
    deadline = time.monotonic() + timeout_s
    pause, scanned, peak = 0.001, -math.inf, 0
    members, marks = [proc.pid], {}
    while True:
        if proc.poll() is not None:
            return Finished(proc.returncode, peak)
        now = time.monotonic()
        if now - scanned >= GROUP_SCAN_S:
            members, scanned = _group_members(proc.pid), now
        for pid in members:
            marks[pid] = max(marks.get(pid, 0), _high_water(pid))
        peak = max(peak, sum(marks.values()))
        left = deadline - now
        if left <= 0:
            raise subprocess.TimeoutExpired(proc.args, timeout_s)
        time.sleep(min(pause, left))
        pause = min(2 * pause, WAIT_POLL_MAX_S)


def _high_water(pid: int) -> int:
    """``VmHWM`` of ``pid`` in bytes (0 when it is gone or has no memory of its own)."""
    try:
        with open(f"/proc/{pid}/status", "rb") as f:
            for line in f:
                if line.startswith(b"VmHWM:"):
                    return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _group_members(pgid: int) -> list[int]:
    """The processes of the process group ``pgid`` (the leader first)."""
    members = [pgid]
    try:
        names = os.listdir("/proc")
    except OSError:
        return members
    for name in names:
        if not name.isdigit() or int(name) == pgid:
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                stat = f.read()
            if int(stat.rsplit(b")", 1)[1].split()[2]) == pgid:
                members.append(int(name))
        except (OSError, ValueError, IndexError):
            continue
    return members


def _kill_group(proc: subprocess.Popen, after_exit: bool = False) -> None:
    """SIGKILL the process group ``proc`` leads; ``after_exit``: only once the leader has
    exited (what it left behind), never a running simulator."""
    if after_exit and proc.returncode is None:
        return
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    if proc.returncode is None:
        proc.wait()


def _run_process(cmd: list[str], deck: Path, run_dir: Path, timeout_s: float, backend: str,
                 exit_reasons: dict[int, FailureKind] | None = None, cwd: Path | None = None
                 ) -> SimulationResult:
    """Run ``cmd`` with stderr in ``simulator.log`` and stdout in ``simulator.stdout``.

    A negative return code (killed by a signal, e.g. out of memory) is ``killed``; other
    non-zero codes are looked up in ``exit_reasons`` and default to ``crash``. A program that
    cannot be started (missing, not executable) is a ``crash`` with that reason.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    log_path, out_path = run_dir / "simulator.log", run_dir / "simulator.stdout"
    start = time.perf_counter()
    try:
        with open(log_path, "wb") as log, open(out_path, "wb") as out:
            proc = run_in_own_group(cmd, stdout=out, stderr=log, timeout_s=timeout_s,
                                    cwd=cwd or run_dir)
    except subprocess.TimeoutExpired:
        raise SimulationError(FailureKind.TIMEOUT, f"no result after {timeout_s:g} s (raise timeout_s "
                              "if the model is just slow)", run_dir,
                              _failure_log(run_dir, log_path, out_path))
    except OSError as exc:  # FileNotFoundError, PermissionError, ...
        raise SimulationError(FailureKind.CRASH, f"cannot start {cmd[0]}: {exc.strerror or exc} (install "
                              "the simulator or fix the command template)", run_dir) from exc
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        reason = (FailureKind.KILLED if proc.returncode < 0
                  else (exit_reasons or {}).get(proc.returncode, FailureKind.CRASH))
        raise SimulationError(reason, f"{backend} exited with code {proc.returncode}", run_dir,
                              _failure_log(run_dir, log_path, out_path))
    summary = run_dir / f"{deck.stem.upper()}.SMSPEC"
    if not summary.exists():
        found = sorted(run_dir.glob("*.SMSPEC"))
        if len(found) != 1:
            raise SimulationError(FailureKind.NO_OUTPUT, f"{backend} finished but wrote no summary "
                                  f"({summary.name}) to {run_dir}", run_dir,
                                  _failure_log(run_dir, log_path, out_path))
        summary = found[0]
    return SimulationResult(summary, run_dir, wall, backend, proc.peak_rss_bytes or None)


@dataclass(frozen=True)
class OpmFlow:
    """OPM Flow via the pip ``opm-simulators`` bindings, in a fresh subprocess per run."""

    timeout_s: float = 600.0
    extra_args: tuple[str, ...] = ()
    name: str = "opm-flow-python"

    def run(self, deck: Path, run_dir: Path) -> SimulationResult:
        # The deck is passed by name from its own folder: OPM's option parser would take a path
        # holding '=' (a run folder like 'skin=5') for an option.
        deck, run_dir = Path(deck).resolve(), Path(run_dir).resolve()
        cmd = [sys.executable, "-m", "hmcore.simulation.opm_runner", deck.name, str(run_dir), *self.extra_args]
        return _run_process(cmd, deck, run_dir, self.timeout_s, self.name,
                            {2: FailureKind.PARSE_ERROR, 3: FailureKind.NO_CONVERGENCE},
                            cwd=deck.parent)


@dataclass(frozen=True)
class CommandLineSimulator:
    """Any simulator run as a shell-free command built from a template.

    Placeholders: ``{deck}`` (absolute deck path), ``{run_dir}``, ``{case}`` (deck name without
    extension), ``{threads}`` and ``{processes}`` (per run, from the case's ``[simulator]``).
    The simulator must leave ``CASE.SMSPEC``/``CASE.UNSMRY`` in ``run_dir``.
    """

    template: str = ("flow {deck} --output-dir={run_dir} --enable-terminal-output=false "
                     "--threads-per-process=1")
    timeout_s: float = 600.0
    name: str = "command-line"
    threads: int = 1
    processes: int = 1

    def command(self, deck: Path, run_dir: Path) -> list[str]:
        return [part.format(deck=deck, run_dir=run_dir, case=deck.stem, threads=self.threads,
                            processes=self.processes)
                for part in shlex.split(self.template)]

    def run(self, deck: Path, run_dir: Path) -> SimulationResult:
        cmd = self.command(deck, run_dir)
        return _run_process(cmd, deck, run_dir, self.timeout_s, f"{self.name}:{cmd[0]}")


def make_simulator(spec: str | None, timeout_s: float = 600.0, threads: int = 1,
                   stop_step: int | None = None, processes: int = 1) -> Simulator:
    """Build a simulator from a user string: ``None``/``"opm"`` or a command template.

    ``threads``: OpenMP threads per run (OPM's ``--threads-per-process``); ``stop_step``: end
    each run after this report step. A command template states its own options (``{threads}``
    and ``{processes}`` stand for the case's threads and MPI processes per run) and always
    runs the whole schedule."""
    if spec in (None, "", "opm", "opm-flow"):
        extra = (() if threads == 1 else (f"--threads-per-process={threads}",)) + \
            (() if stop_step is None else (f"--hmflow-stop-step={stop_step}",))
        return OpmFlow(timeout_s=timeout_s, extra_args=extra)
    return CommandLineSimulator(template=spec, timeout_s=timeout_s, threads=threads,
                                processes=processes)
