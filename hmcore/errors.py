"""Errors hmflow raises: input problems (all reported at once) and simulation failures."""

from __future__ import annotations

from enum import Enum
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class Problem:
    """One thing wrong with the user's input.

    ``where`` names the file and, when known, the row, line or key (``observed.csv row 14``).
    ``what`` states the broken rule with the offending values; ``fix`` says how to repair it.
    """

    where: str
    what: str
    fix: str = ""

    def __str__(self) -> str:
        text = f"{self.where}: {self.what}"
        return f"{text} (fix: {self.fix})" if self.fix else text


class CaseError(ValueError):
    """Raised when a case (case file, deck, observed history, parameters) is invalid.

    Carries every problem found, not only the first, so the user can fix them in one pass.
    """

    def __init__(self, problems: list[Problem]):
        self.problems = list(problems)
        lines = [f"{len(self.problems)} problem(s) found:"] + [f"  - {p}" for p in self.problems]
        super().__init__("\n".join(lines))


class FailureKind(str, Enum):
    """Why a simulator call gave no usable result, decided from facts (exit code, signal,
    timer, files), never from the simulator's message text."""

    PARSE_ERROR = "parse_error"            # the simulator refused the deck (its exit code)
    NO_CONVERGENCE = "no_convergence"      # it stopped before the end of the schedule
    CRASH = "crash"                        # any other non-zero exit, or it could not start
    TIMEOUT = "timeout"                    # no result within timeout_s (its process group killed)
    KILLED = "killed"                      # ended by a signal (out of memory, a lost node)
    NO_OUTPUT = "no_output"                # exit 0 but no summary file
    UNREADABLE_OUTPUT = "unreadable_output"  # a summary that cannot be read (garbage, empty)
    INVALID_VALUES = "invalid_values"      # responses that are not finite numbers
    NO_MATCH = "no_match"                  # no simulated record near any observation
    NOT_RUNNABLE = "not_runnable"          # physically impossible values, not simulated

    @property
    def transient(self) -> bool:
        """Worth running again: only a call ended from outside (a signal, a lost worker)."""
        return self is FailureKind.KILLED


@dataclass
class SimulationError(RuntimeError):
    """A simulation that did not produce usable results.

    ``reason`` is a :class:`FailureKind` (a ``str``: it compares equal to its value);
    ``log_tail`` holds the end of the simulator's stderr/log.
    """

    reason: FailureKind
    message: str
    run_dir: Path | None = None
    log_tail: str = ""
    details: dict = field(default_factory=dict)

    def __str__(self) -> str:
        where = f" in {self.run_dir}" if self.run_dir else ""
        tail = f"\n--- log tail ---\n{self.log_tail}" if self.log_tail else ""
        return f"simulation failed ({self.reason}){where}: {self.message}{tail}"
