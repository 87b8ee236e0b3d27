"""The parameter rules of a campaign, a benchmark and a diagnosis: a known method, a budget and
worker count the method can run with, a known task runner, and a case with scalar parameters
for the method to move.

The one home of these rules: a flow checks them and returns a Failed state
(:mod:`flows.refuse`); the command line checks them before it starts Prefect and exits 2. So
this module imports no Prefect (Prefect reads its settings once, on import, and the command
line sets them after its input is checked).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from flows.runners import RUNNERS
from hmcore.calibration.registry import METHODS

if TYPE_CHECKING:  # the case module imports pandas: keeps `hmflow --help` fast
    from hmcore.model.case import Case


def as_parameter(name: str) -> str:
    """A flow parameter spelled as the flow names it (``task_runner``)."""
    return name


def input_problems(agent: str | None = None, budget: int | None = None,
                   workers: int | None = None, task_runner: str | None = None, *,
                   spell: Callable[[str], str] = as_parameter) -> list[str]:
    """Every rule the given parameters break (none given: not checked); [] when they are fine.

    ``spell`` names a parameter as its user gave it: the flow's parameter name by default, an
    option (``--task-runner``) on the command line. The case file is checked by loading it."""
    problems = []
    if agent is not None and agent not in METHODS:
        problems.append(f"{spell('agent')} must be one of {list(METHODS)}, got {agent!r}")
    elif agent is not None and budget is not None and workers is not None:
        # the methods package imports numpy and gymnasium: keeps `hmflow --help` fast
        from hmcore.calibration.methods import budget_problem

        problem = budget_problem(agent, budget, workers)
        if problem:
            problems.append(f"{spell('agent')} {agent}, {spell('budget')} {budget}, "
                            f"{spell('workers')} {workers}: {problem}")
    if task_runner is not None and task_runner not in RUNNERS:
        problems.append(f"{spell('task_runner')} must be one of {list(RUNNERS)}, "
                        f"got {task_runner!r}")
    return problems


def scalar_problems(loaded: Case, latent: bool = False) -> list[str]:
    """A calibration (a campaign's method, a benchmark's, a diagnosis's) moves the case's
    scalar parameters: a case of field parameters only has none, and is refused in one line
    before anything runs; [] for any other case (its fields, if any, are left at the deck's
    values: they are the ensemble smoother's, docs/ensembles.md). A campaign and a benchmark
    (``latent``) also move a ``[latent]`` case's fields by their prior's modes; a diagnosis
    does not, and refuses such a case."""
    if loaded.latent is not None and not latent:
        return [(f"case {loaded.name} ({loaded.source}) has a [latent] section: its fields are "
                 "moved by their prior's modes in a campaign or a benchmark (hmflow run, "
                 "hmflow bench), not in a diagnosis (fix: remove [latent] to diagnose the "
                 "scalar parameters)")]
    if loaded.space.parameters or not loaded.fields or loaded.latent is not None:
        return []
    names = ", ".join(f.name for f in loaded.fields)
    return [(f"case {loaded.name} ({loaded.source}) has field parameters only ({names}) and "
             "no scalar parameter for a calibration method to move (fix: add a scalar "
             "[[parameters]] table, e.g. kind = \"multiply\", or a [latent] section, which moves "
             "the fields by their prior's leading modes; or match the fields with the "
             "ensemble smoother, hmflow ensemble: docs/ensembles.md)")]


def ensemble_problems(loaded: Case) -> list[str]:
    """An ensemble run (``hmflow ensemble``) matches field parameters: a case without one is
    refused in one line, and so is a scalar multiplier of a keyword a field writes (the
    member's values replace the keyword after every GRID edit, so the multiplier would
    change nothing); [] when the case can run."""
    if not loaded.fields:
        return [(f"case {loaded.name} ({loaded.source}) has no field parameter for an ensemble "
                 "to match (fix: add a [[parameters]] table with kind = \"field\", "
                 "docs/ensembles.md; scalar parameters alone are calibrated by hmflow run, "
                 "e.g. --agent esmda)")]
    written = {k: f.name for f in loaded.fields for k in f.written}
    return [(f"case {loaded.name} ({loaded.source}): parameter '{p.name}' multiplies "
             f"{k}, which field '{written[k]}' sets in every member (fix: remove "
             f"'{p.name}', or its keyword {k}; the field's prior mean is the multiplier)")
            for p in loaded.space.parameters if p.kind == "multiply"
            for k in (x.upper() for x in p.keywords) if k in written]

