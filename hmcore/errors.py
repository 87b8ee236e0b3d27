"""Errors hmflow raises: input problems (all reported at once) and simulation failures."""

from __future__ import annotations

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


@dataclass
class SimulationError(RuntimeError):
    """A simulation that did not produce usable results.

    ``reason`` is one of ``parse_error``, ``timeout``, ``killed`` (by a signal), ``crash``,
    ``no_convergence``, ``no_output``; ``log_tail`` holds the end of the simulator's stderr/log.
    """

    reason: str
    message: str
    run_dir: Path | None = None
    log_tail: str = ""
    details: dict = field(default_factory=dict)

    def __str__(self) -> str:
        where = f" in {self.run_dir}" if self.run_dir else ""
        tail = f"\n--- log tail ---\n{self.log_tail}" if self.log_tail else ""
        return f"simulation failed ({self.reason}){where}: {self.message}{tail}"
