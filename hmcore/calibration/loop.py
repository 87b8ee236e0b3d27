"""The calibration loop: ask a proposer for W actions, evaluate them together, tell the results.

The loop never runs the simulator itself: ``evaluate_batch(jobs) -> records`` is injected (the
Prefect flow submits one task per job to a task runner; tests pass a plain function). Every
call goes through one :class:`~hmcore.calibration.calls.BudgetedCalls`: records already in
``done`` (a resumed campaign's journal) are replayed to the proposer instead of being simulated
again, and a point the campaign has simulated already is answered with its record without a
call (the loop then asks for more until the budget is spent). The last call of the budget
evaluates the proposer's recommendation (for SAC, the deterministic policy), so the campaign
ends on what the agent learned, not only on samples, when the proposer says it is worth a call
(``exploit_last``) and the campaign has not simulated that point already.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from hmcore.calibration.calls import BudgetedCalls, Job
from hmcore.calibration.methods.base import Driver, Proposal, Proposer
from hmcore.calibration.objective import Objective, feedback_of
from hmcore.model.parameters import ParameterSpace

__all__ = ["best_record", "calibrate", "feedback_of"]


def calibrate(proposer: Proposer | Driver, space: ParameterSpace,
              evaluate_batch: Callable[[list[Job]], list[dict]], budget: int, workers: int,
              done: dict[int, dict] | None = None, exploit_last: bool | None = None,
              precheck: Callable[[dict[str, float]], frozenset[str]] | None = None,
              objective: Objective | None = None,
              on_refine: Callable[[Objective], None] | None = None) -> list[dict]:
    """Run ``budget`` simulator calls, ``workers`` at a time; return every record in call order.

    Each record must carry ``reward``, ``E`` (NaN/None for failures) and ``penalty``. A
    :class:`~hmcore.calibration.methods.base.Driver` (``lm``, ``esmda``, ``sac-paper``) runs
    its own loop over the same calls instead. ``precheck``: the kinds of physics check a
    point's parameter values break before any run
    (:class:`~hmcore.calibration.calls.PhysicsPrecheck`), for the methods that use it.
    ``objective``: what the methods are told of each call (default: E, the record's reward);
    its noise is refined during the campaign (:class:`~hmcore.calibration.calls.BudgetedCalls`),
    ``on_refine`` hears each refined objective.
    """
    if budget < 1 or workers < 1:
        raise ValueError(f"budget >= 1 and workers >= 1 must hold, got budget={budget}, "
                         f"workers={workers}")
    calls = BudgetedCalls(space, evaluate_batch, budget, done, proposer.name,
                          reuse=getattr(proposer, "reuses_points", True), precheck=precheck,
                          objective=objective, on_refine=on_refine)
    if isinstance(proposer, Driver):
        return proposer.drive(calls, workers)
    if exploit_last is None:  # the proposer says whether its recommendation is worth a call
        exploit_last = bool(getattr(proposer, "exploit_last", False))
    while calls.left > 0:
        # a proposer may return fewer than asked (CMA-ES at the end of a generation)
        proposals = proposer.ask(min(workers, calls.left))
        n = len(proposals)
        if n < 1:
            raise RuntimeError(f"proposer {proposer.name!r} proposed nothing at call "
                               f"{len(calls.records)}")
        phases = ["explore"] * n
        if exploit_last and n == calls.left:
            best = np.asarray(proposer.recommend(), np.float32)
            if calls.worth_a_call(best):
                proposals[0] = Proposal(best, proposals[0].observation, proposals[0].lane)
                phases[0] = "exploit"  # key -1
        batch = calls.submit([p.action for p in proposals], [p.lane for p in proposals], phases)
        told = [Proposal(np.asarray(r["action"], np.float32), p.observation, p.lane, p.key)
                for r, p in zip(batch, proposals)]
        proposer.tell(told, [calls.objective.feedback(r) for r in batch])
    return calls.records


def best_record(records: list[dict], objective: str = "E") -> dict | None:
    """The COMPLETE record (never INVALID or FAIL) of the lowest value of ``objective`` (the
    record key: ``E``, or ``likelihood`` in a consolidated record, under the campaign's final
    noise); None when none."""
    ok = [r for r in records if r.get("status") == "COMPLETE" and r.get(objective) is not None
          and math.isfinite(r[objective])]
    return min(ok, key=lambda r: r[objective]) if ok else None
