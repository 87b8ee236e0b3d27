"""Bad input given to a flow run (from the UI's run form, a deployment's parameters or the
API) ends the run before any simulator time as a Failed state with one clear message: which
file, key or parameter, what is wrong and how to fix it; no traceback in the run's log.
(The command line checks the same before it starts Prefect at all.)"""

from __future__ import annotations

from prefect import get_run_logger
from prefect.states import Failed, State

from hmcore.errors import CaseError

USER_ERRORS = (CaseError, ValueError, FileNotFoundError, NotADirectoryError, PermissionError)


def refused(exc: BaseException) -> State:
    """Log the problem as one line and return the Failed state the flow returns."""
    if isinstance(exc, CaseError):
        text = "; ".join(str(p) for p in exc.problems)
    else:
        text = " ".join(str(exc).split()) or type(exc).__name__
    get_run_logger().error(f"refused before any simulation: {text}")
    return Failed(message=f"refused before any simulation: {text}")


def input_problems(agent: str | None = None, budget: int | None = None,
                   workers: int | None = None, task_runner: str | None = None) -> list[str]:
    """The parameter rules a flow checks itself (the case file is checked by loading it)."""
    from hmcore.calibration.methods import METHODS, budget_problem
    from flows.runners import RUNNERS

    problems = []
    if agent is not None and agent not in METHODS:
        problems.append(f"agent must be one of {list(METHODS)}, got {agent!r}")
    elif agent is not None and budget is not None and workers is not None:
        problem = budget_problem(agent, budget, workers)
        if problem:
            problems.append(f"agent {agent}, budget {budget}, workers {workers}: {problem}")
    if task_runner is not None and task_runner not in RUNNERS:
        problems.append(f"task_runner must be one of {list(RUNNERS)}, got {task_runner!r}")
    return problems
