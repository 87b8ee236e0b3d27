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

import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from hmcore.errors import SimulationError

LOG_TAIL_CHARS = 4000


@dataclass(frozen=True)
class SimulationResult:
    """Where a finished run left its summary (``CASE.SMSPEC``) and how long it took."""

    summary_path: Path
    run_dir: Path
    wall_time_s: float
    backend: str


class Simulator(Protocol):
    """Runs ``deck`` with all output in ``run_dir``; raises SimulationError on failure."""

    name: str

    def run(self, deck: Path, run_dir: Path) -> SimulationResult: ...


def _tail(text: str) -> str:
    return text[-LOG_TAIL_CHARS:]


def _run_process(cmd: list[str], deck: Path, run_dir: Path, timeout_s: float, backend: str,
                 log_name: str, exit_reasons: dict[int, str] | None = None) -> SimulationResult:
    """Run ``cmd`` (stdout discarded, stderr to the log); map failures to SimulationError.

    A negative return code (killed by a signal, e.g. out of memory) is ``killed``; other
    non-zero codes are looked up in ``exit_reasons`` and default to ``crash``.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    log_path = run_dir / log_name
    start = time.perf_counter()
    try:
        with open(log_path, "wb") as log:
            proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=log, timeout=timeout_s,
                                  check=False, cwd=run_dir)
    except subprocess.TimeoutExpired:
        raise SimulationError("timeout", f"no result after {timeout_s:.0f} s (raise timeout_s "
                              "if the model is just slow)", run_dir,
                              _tail(log_path.read_text(errors="replace")))
    wall = time.perf_counter() - start
    log_text = log_path.read_text(errors="replace")
    if proc.returncode != 0:
        reason = ("killed" if proc.returncode < 0
                  else (exit_reasons or {}).get(proc.returncode, "crash"))
        raise SimulationError(reason, f"{backend} exited with code {proc.returncode}", run_dir,
                              _tail(log_text))
    summary = run_dir / f"{deck.stem.upper()}.SMSPEC"
    if not summary.exists():
        found = sorted(run_dir.glob("*.SMSPEC"))
        if len(found) != 1:
            raise SimulationError("no_output", f"{backend} finished but wrote no summary "
                                  f"({summary.name}) to {run_dir}", run_dir, _tail(log_text))
        summary = found[0]
    return SimulationResult(summary, run_dir, wall, backend)


@dataclass(frozen=True)
class OpmFlow:
    """OPM Flow via the pip ``opm-simulators`` bindings, in a fresh subprocess per run."""

    timeout_s: float = 600.0
    extra_args: tuple[str, ...] = ()
    name: str = "opm-flow-python"

    def run(self, deck: Path, run_dir: Path) -> SimulationResult:
        cmd = [sys.executable, "-m", "hmcore.opm_runner", str(deck), str(run_dir), *self.extra_args]
        return _run_process(cmd, deck, run_dir, self.timeout_s, self.name, "simulator.log",
                            {2: "parse_error", 3: "no_convergence"})


@dataclass(frozen=True)
class CommandLineSimulator:
    """Any simulator run as a shell-free command built from a template.

    Placeholders: ``{deck}`` (absolute deck path), ``{run_dir}``, ``{case}`` (deck name without
    extension). The simulator must leave ``CASE.SMSPEC``/``CASE.UNSMRY`` in ``run_dir``.
    """

    template: str = "flow {deck} --output-dir={run_dir} --enable-terminal-output=false"
    timeout_s: float = 600.0
    name: str = "command-line"

    def command(self, deck: Path, run_dir: Path) -> list[str]:
        return [part.format(deck=deck, run_dir=run_dir, case=deck.stem)
                for part in shlex.split(self.template)]

    def run(self, deck: Path, run_dir: Path) -> SimulationResult:
        cmd = self.command(deck, run_dir)
        try:
            return _run_process(cmd, deck, run_dir, self.timeout_s, f"{self.name}:{cmd[0]}",
                                "simulator.log")
        except FileNotFoundError as exc:
            raise SimulationError("crash", f"simulator executable not found: {cmd[0]} "
                                  "(install it or fix the command template)", run_dir) from exc


def make_simulator(spec: str | None, timeout_s: float = 600.0) -> Simulator:
    """Build a simulator from a user string: ``None``/``"opm"`` or a command template."""
    if spec in (None, "", "opm", "opm-flow"):
        return OpmFlow(timeout_s=timeout_s)
    return CommandLineSimulator(template=spec, timeout_s=timeout_s)
