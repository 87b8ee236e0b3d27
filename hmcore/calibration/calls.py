"""Simulator calls: what one call is (:class:`Job`), the one replay path of a resumed campaign
(:func:`replay_or_evaluate`), and the calls of a driver (a method with its own loop: LM, ES-MDA,
SB3's learn()).

:class:`BudgetedCalls` numbers the calls, replays the ones a resumed campaign already journaled
instead of evaluating them again, evaluates the rest through the injected ``evaluate_batch``
(W at a time on the caller's task runner) and stops the method with :class:`BudgetExhausted`
the moment the budget is spent. Every run counts as a call: finite-difference Jacobian runs
and ensemble members included.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from hmcore.model.parameters import ParameterSpace

ACTION_MATCH_ATOL = 1e-5


@dataclass(frozen=True)
class Job:
    """One simulator call to make: call index, physical values and the action behind them."""

    index: int
    values: dict[str, float]
    action: tuple[float, ...]
    lane: int
    phase: str  # "explore" (sampled) or "exploit" (the proposer's recommendation)


def check_replay(record: dict, job, method: str) -> dict:
    """``record`` when it is the call ``job`` asks for; a resumed campaign whose method asks
    for another action than the journal holds is refused, never mixed."""
    if not np.allclose(record["action"], job.action, atol=ACTION_MATCH_ATOL):
        raise RuntimeError(
            f"resumed {method} campaign diverged at call {job.index}: the journal has action "
            f"{record['action']}, the replayed method asks {list(job.action)}; the journal is "
            "kept as it is - start a new --campaign name to rerun")
    return record


def replay_or_evaluate(jobs: list[Job], done: dict[int, dict],
                       evaluate_batch: Callable[[list[Job]], list[dict]], method: str
                       ) -> list[dict]:
    """The records of ``jobs`` in order: a call the journal (``done``) holds is replayed, after
    checking it is the call asked for (before anything new runs); the others are evaluated
    together through ``evaluate_batch``."""
    replayed = {j.index: check_replay(done[j.index], j, method) for j in jobs if j.index in done}
    todo = [j for j in jobs if j.index not in done]
    fresh = {r["index"]: r for r in (evaluate_batch(todo) if todo else [])}
    return [replayed.get(j.index) or fresh[j.index] for j in jobs]


class BudgetExhausted(Exception):
    """Raised inside a method's loop when its budget of simulator calls is spent."""


class BudgetedCalls:
    def __init__(self, space: ParameterSpace, evaluate_batch: Callable[[list], list[dict]],
                 budget: int, done: dict[int, dict] | None = None, method: str = ""):
        self.space = space
        self.evaluate_batch = evaluate_batch
        self.budget = budget
        self.done = done or {}
        self.method = method
        self.records: list[dict] = []

    @property
    def left(self) -> int:
        return self.budget - len(self.records)

    def run(self, actions: np.ndarray, lanes: list[int] | None = None,
            phase: str = "explore", phases: list[str] | None = None) -> list[dict]:
        """Evaluate each row of ``actions`` (clipped to [-1, 1]) as one call (``phases``: each
        call's phase, default ``phase`` for all); returns their records in order. When the
        budget ends inside the batch, the calls that fit are made and
        :class:`BudgetExhausted` is raised."""
        actions = np.clip(np.atleast_2d(np.asarray(actions, float)), -1.0, 1.0)
        fit = actions[: max(0, self.left)]
        start = len(self.records)
        jobs = [Job(start + i, self.space.to_values(a), tuple(float(x) for x in a),
                    (lanes[i] if lanes else i), phases[i] if phases else phase)
                for i, a in enumerate(fit)]
        batch = replay_or_evaluate(jobs, self.done, self.evaluate_batch, self.method)
        self.records.extend(batch)
        if len(fit) < len(actions):
            raise BudgetExhausted(f"{self.budget} calls spent")
        return batch
