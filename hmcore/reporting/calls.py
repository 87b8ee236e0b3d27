"""What became of a campaign's simulator calls, in one vocabulary for the report's Markdown,
HTML and JSON: each call is **valid**, **penalised** or **failed**; a penalised call is counted
under each physics check it broke, named as a reservoir engineer reads it with one sentence of
what the check tests and its limit (:mod:`hmcore.scoring.physics`); a failed call under the
reason it failed (:class:`hmcore.errors.FailureKind`).

The stored states stay Optuna's (``COMPLETE``, ``INVALID``, ``FAIL``: the records' and
``report.json``'s ``status_counts``); :data:`STATES` says each in words.
"""

from __future__ import annotations

from dataclasses import dataclass

import pandas as pd

from hmcore.model.case import PhysicsSettings
from hmcore.scoring.physics import Check, check_name, check_sentence

STATES = (("COMPLETE", "valid", "simulated, and every physics check passed: only a valid call "
           "can be the best case"),
          ("INVALID", "penalised", "simulated, but a physics check failed: its misfit carries a "
           "penalty and it is never the best case"),
          ("FAIL", "failed", "no usable result (the simulator stopped, timed out or was not run "
           "on physically impossible values): no misfit"))
"""(stored state, the word the report uses, what it means)."""


@dataclass(frozen=True)
class CheckCount:
    """One physics check: its stored key, its name, what it tests, the calls it penalised."""

    key: str
    name: str
    tests: str
    penalised: int


@dataclass(frozen=True)
class Calls:
    """A campaign's calls by state (the report's words), the physics checks with the calls
    each penalised, and the failed calls by reason."""

    total: int
    states: dict[str, int]
    checks: tuple[CheckCount, ...]
    failures: dict[str, int]

    @property
    def text(self) -> str:
        """'162 valid, 38 penalised, 0 failed'."""
        return ", ".join(f"{n} {word}" for word, n in self.states.items())

    def document(self) -> dict:
        """The JSON form: ``call_states`` (word -> calls), ``physics_checks``,
        ``failure_reasons`` (stored reason -> calls)."""
        return {"call_states": dict(self.states),
                "physics_checks": [{"check": c.key, "name": c.name, "tests": c.tests,
                                    "penalised_calls": c.penalised} for c in self.checks],
                "failure_reasons": dict(self.failures)}


def count_calls(table: pd.DataFrame, physics: dict | None) -> Calls:
    """:class:`Calls` of an evaluations table (``status``, ``violation_kinds``: the checks a
    call broke, comma-separated; ``failure``) under the case's ``[physics]`` settings (the
    case document's ``physics``; defaults when absent). A penalised call counts once under each
    check it broke; every check is listed, those that penalised none with 0."""
    settings = PhysicsSettings.model_validate(physics or {})
    status = table["status"] if len(table) else pd.Series(dtype=object)
    raw = status.value_counts().to_dict()
    states = {word: int(raw.get(state, 0)) for state, word, _ in STATES}
    kinds = penalised_by_check(table)
    keys = [c.value for c in Check] + sorted(set(kinds) - {c.value for c in Check})
    checks = tuple(CheckCount(k, check_name(k), check_sentence(k, settings), kinds.get(k, 0))
                   for k in keys)
    return Calls(len(table), states, checks, failure_reasons(table))


def penalised_by_check(table: pd.DataFrame) -> dict[str, int]:
    """Stored check key -> penalised calls that broke it (a call counts once per check)."""
    kinds: dict[str, int] = {}
    if not len(table) or "violation_kinds" not in table:
        return kinds
    for cell in table.loc[table.status == "INVALID", "violation_kinds"].fillna(""):
        for kind in sorted(set(filter(None, str(cell).split(",")))) or ["unspecified"]:
            kinds[kind] = kinds.get(kind, 0) + 1
    return kinds


def failure_reasons(table: pd.DataFrame) -> dict[str, int]:
    """Stored failure reason (:class:`hmcore.errors.FailureKind` value) -> failed calls."""
    if not len(table):
        return {}
    column = "failure" if "failure" in table else "reason"
    reasons = table.loc[table.status == "FAIL", column].fillna("unknown")
    return {str(k).split(":")[0] or "unknown": int(v)
            for k, v in reasons.value_counts().items()}


def reason_words(reason: str) -> str:
    """A stored failure reason as words ('no_convergence' -> 'no convergence')."""
    return reason.replace("_", " ")


def calls_markdown(calls: Calls) -> list[str]:
    """The calls section: the counts in words, what each state means, every physics check
    (name, what it tests and its limit, calls penalised) and the failed calls by reason."""
    lines = ["## Calls: valid, penalised, failed", "",
             f"{calls.total} simulator calls: {calls.text}.", ""]
    lines += [f"- **{word}**: {meaning}." for _, word, meaning in STATES]
    lines += ["", "| physics check | what it tests, and its limit | penalised calls |",
              "|:---|:---|---:|"]
    lines += [f"| {c.name} | {c.tests} | {c.penalised} |" for c in calls.checks]
    if calls.failures:
        lines += ["", "Failed calls by reason: " + ", ".join(
            f"{reason_words(k)} {v}" for k, v in sorted(calls.failures.items())) + "."]
    return lines + [""]


def chart_counts(calls: Calls) -> dict[str, int]:
    """The bars of the failures chart: 'failed: <reason>' and 'penalised: <check name>'."""
    out = {f"failed: {reason_words(k)}": v for k, v in sorted(calls.failures.items())}
    out.update({f"penalised: {c.name}": c.penalised for c in calls.checks if c.penalised})
    return out
