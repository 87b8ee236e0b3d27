"""Bad input given to a flow run (from the UI's run form, a deployment's parameters or the
API) ends the run before any simulator time as a Failed state with one clear message: which
file, key or parameter, what is wrong and how to fix it; no traceback in the run's log.
The parameter rules are :func:`flows.inputs.input_problems` and
:func:`flows.inputs.scalar_problems`, which the command line checks too, before it starts
Prefect at all."""

from __future__ import annotations

from prefect import get_run_logger
from prefect.states import Failed, State

from flows.inputs import input_problems, scalar_problems
from hmcore.errors import CaseError

__all__ = ["USER_ERRORS", "input_problems", "refused", "scalar_problems"]

USER_ERRORS = (CaseError, ValueError, FileNotFoundError, NotADirectoryError, PermissionError)


def refused(exc: BaseException) -> State:
    """Log the problem as one line and return the Failed state the flow returns."""
    if isinstance(exc, CaseError):
        text = "; ".join(str(p) for p in exc.problems)
    else:
        text = " ".join(str(exc).split()) or type(exc).__name__
    get_run_logger().error(f"refused before any simulation: {text}")
    return Failed(message=f"refused before any simulation: {text}")
