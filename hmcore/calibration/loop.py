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
from hmcore.calibration.methods.base import Driver, Feedback, Proposal, Proposer
from hmcore.model.parameters import ParameterSpace


def feedback_of(record: dict) -> Feedback:
    """Reward and observed E (E, or the penalty of a failed run) from an evaluation record."""
    E = record.get("E")
    scored = E is not None and math.isfinite(E)
    e_obs = E if scored else record["penalty"]
    worst = record.get("E_worst")
    return Feedback(float(record["reward"]), float(e_obs), scored,
                    float(record.get("penalty") or 0.0) if scored else 0.0,
                    float(worst) if scored and worst is not None and math.isfinite(worst)
                    else None)


def calibrate(proposer: Proposer | Driver, space: ParameterSpace,
              evaluate_batch: Callable[[list[Job]], list[dict]], budget: int, workers: int,
              done: dict[int, dict] | None = None, exploit_last: bool | None = None,
              precheck: Callable[[dict[str, float]], frozenset[str]] | None = None
              ) -> list[dict]:
    """Run ``budget`` simulator calls, ``workers`` at a time; return every record in call order.

    Each record must carry ``reward``, ``E`` (NaN/None for failures) and ``penalty``. A
    :class:`~hmcore.calibration.methods.base.Driver` (``lm``, ``esmda``, ``sac-paper``) runs
    its own loop over the same calls instead. ``precheck``: the kinds of physics check a
    point's parameter values break before any run
    (:class:`~hmcore.calibration.calls.PhysicsPrecheck`), for the methods that use it.
    """
    if budget < 1 or workers < 1:
        raise ValueError(f"budget >= 1 and workers >= 1 must hold, got budget={budget}, "
                         f"workers={workers}")
    calls = BudgetedCalls(space, evaluate_batch, budget, done, proposer.name,
                          reuse=getattr(proposer, "reuses_points", True), precheck=precheck)
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
        proposer.tell(told, [feedback_of(r) for r in batch])
    return calls.records


def best_record(records: list[dict]) -> dict | None:
    """The lowest-E record among COMPLETE ones (never INVALID or FAIL); None when none."""
    ok = [r for r in records if r.get("status") == "COMPLETE" and r.get("E") is not None
          and math.isfinite(r["E"])]
    return min(ok, key=lambda r: r["E"]) if ok else None
