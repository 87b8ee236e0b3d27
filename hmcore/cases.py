"""A user's case argument: a case TOML's path, or the name of a built-in case that hmflow
writes itself on first use (``synthetic``: :mod:`hmcore.scenarios.synthetic`). The entry of
``check``, ``run``, ``evaluate``, ``diagnose`` and ``bench``; the case file itself is read and
validated by :mod:`hmcore.model.case`.
"""

from __future__ import annotations

from pathlib import Path

from hmcore.model.case import BUILTIN_CASES, Case, case_file_name, load_case_file
from hmcore.scenarios.synthetic import ensure_synthetic_case

__all__ = ["BUILTIN_CASES", "case_name", "load_case", "resolve_case_path"]


def resolve_case_path(case: str | Path) -> Path:
    """A TOML path as given, or the built-in case's file (``synthetic``: generated on first
    use)."""
    if str(case) == "synthetic":
        return ensure_synthetic_case()
    return Path(case)


def case_name(case: str | Path) -> str:
    """The ``[case] name`` of a case TOML (cheap: no deck or history is read), or the name of a
    built-in case; ValueError when the file or the name is missing."""
    if str(case) in BUILTIN_CASES:
        return str(case)
    return case_file_name(Path(case))


def load_case(case: str | Path) -> Case:
    """Load and validate a case (a path, or a built-in case's name); CaseError with every
    problem found (:func:`hmcore.model.case.load_case_file`)."""
    return load_case_file(resolve_case_path(case) if str(case) in BUILTIN_CASES else case)
