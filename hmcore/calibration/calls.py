"""Simulator calls: what one call is (:class:`Job`), the one replay path of a resumed campaign
(:func:`replay_or_evaluate`), and the calls of a campaign (:class:`BudgetedCalls`), which the
loop and every driver (a method with its own loop: LM, ES-MDA, SB3's learn()) make through.

:class:`BudgetedCalls` numbers the calls, replays the ones a resumed campaign already journaled
instead of evaluating them again, evaluates the rest through the injected ``evaluate_batch``
(W at a time on the caller's task runner) and stops the method with :class:`BudgetExhausted`
the moment the budget is spent. Every run counts as a call: finite-difference Jacobian runs
and ensemble members included.

A point the campaign has already simulated (the same parameter values, to
:data:`POINT_ATOL` in scaled coordinates: :class:`SimulatedPoints`) is not simulated again:
the method is handed the record of its first call, and no call is spent. Resuming stays exact
because the decision depends only on the points the method was handed before, in order, which
a resumed campaign replays identically; a journal written before points were reused (a call
that simulated a point again) is replayed as it is. A method that keeps asking for simulated
points cannot stall a campaign: after ``budget`` reused points, a point is simulated again.

What a point's parameter values decide before any simulator time (the physics checks on the
deck's cells, :class:`PhysicsPrecheck`) a method may ask through :meth:`BudgetedCalls.breaks`.

The calls hold the campaign's :class:`~hmcore.calibration.objective.Objective` (what a method
is told of a call, and which call is best) and refine its noise from the residuals of the best
call so far (:meth:`BudgetedCalls.refine_noise`): when a method asks (``lm`` at the end of a
descent) and when the calls made pass :data:`REFINE_AT` of the budget (after the batch
that passes it, whatever the method), at most
:data:`MAX_REFINEMENTS` times, each time from another best call. Resuming stays exact: the
decision and the noise are functions of the records in call order, which a resumed campaign
replays identically.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hmcore.calibration.objective import Objective
from hmcore.eclipse.deck_info import DeckInfo
from hmcore.model.case import Case, PhysicsSettings
from hmcore.model.parameters import ParameterSpace
from hmcore.scoring.physics import check_physics

ACTION_MATCH_ATOL = 1e-5
POINT_ATOL = 1e-6
"""Two calls are of the same point when every parameter agrees to this in scaled coordinates
(a millionth of its half range; the whole box is 2 wide): far below a finite-difference step
(0.05) and any step a method means to take."""


REFINE_AT = (0.25, 0.5)
"""Shares of the budget after which the noise is refined (when the best call changed): a
method that never asks (a proposer) still fits under a noise refined from its fit."""
MAX_REFINEMENTS = 3
"""Refinements of the noise in one campaign at most (the diagnosis's iteration converges in
two or three)."""


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
    if not same_action(record, job.action):
        raise RuntimeError(
            f"resumed {method} campaign diverged at call {job.index}: the journal has action "
            f"{record['action']}, the replayed method asks {list(job.action)}; the journal is "
            "kept as it is - start a new --campaign name to rerun")
    return record


def same_action(record: dict, action) -> bool:
    """Whether the journaled ``record`` is the call of ``action`` (to :data:`ACTION_MATCH_ATOL`)."""
    return bool(np.allclose(record["action"], action, atol=ACTION_MATCH_ATOL))


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


class SimulatedPoints:
    """Points by their parameter values, each with what the campaign keeps of it (the record
    of its first call): :meth:`find` is the first point within :data:`POINT_ATOL` of the given
    values, in the space's scaled coordinates (log-scaled where a parameter is)."""

    def __init__(self, space: ParameterSpace):
        self.space = space
        self._u = np.empty((0, space.dim))
        self._items: list[Any] = []

    def __len__(self) -> int:
        return len(self._items)

    def find(self, values: dict[str, float]) -> Any | None:
        if not self._items:
            return None
        distance = np.max(np.abs(self._u - self.space.to_action(values)), axis=1)
        k = int(np.argmin(distance))
        return self._items[k] if distance[k] <= POINT_ATOL else None

    def add(self, values: dict[str, float], item: Any) -> None:
        """Keep ``item`` for the point of ``values`` (the first one kept stays)."""
        if self.find(values) is None:
            self._u = np.vstack([self._u, self.space.to_action(values)[None]])
            self._items.append(item)


@dataclass(frozen=True)
class PhysicsPrecheck:
    """The physics checks a point's parameter values decide alone, before the simulator runs
    (:func:`hmcore.scoring.physics.check_physics` on the deck's cells: porosity and
    permeability limits, kv/kh, the porosity-permeability trend, pore volume, parameter
    ranges). Called with the values, it returns the kinds of check they break."""

    space: ParameterSpace
    info: DeckInfo
    settings: PhysicsSettings

    @classmethod
    def of(cls, case: Case) -> PhysicsPrecheck:
        return cls(case.space, case.info, case.physics)

    def __call__(self, values: dict[str, float]) -> frozenset[str]:
        return frozenset(check_physics(values, self.space, self.info, self.settings).kinds)


class BudgetExhausted(Exception):
    """Raised inside a method's loop when its budget of simulator calls is spent."""


@dataclass
class _Plan:
    """How the rows of one request are answered: a reused record, or the position of a job."""

    rows: list[dict | int] = field(default_factory=list)
    jobs: list[Job] = field(default_factory=list)
    short: bool = False  # the budget ended before every row had its call


class BudgetedCalls:
    """The ``budget`` simulator calls of one campaign (see the module docstring): ``records``
    in call order, the points simulated (``points``), how many asked points were answered
    from them (``reused``); ``reuse=False`` turns reuse off (a method that counts its own
    steps as calls: SB3's ``learn()``). ``precheck``: the kinds of check a point's values
    break (:class:`PhysicsPrecheck`), None when nothing is known before a run."""

    def __init__(self, space: ParameterSpace, evaluate_batch: Callable[[list], list[dict]],
                 budget: int, done: dict[int, dict] | None = None, method: str = "", *,
                 reuse: bool = True,
                 precheck: Callable[[dict[str, float]], frozenset[str]] | None = None,
                 objective: Objective | None = None,
                 on_refine: Callable[[Objective], None] | None = None):
        self.space = space
        self.evaluate_batch = evaluate_batch
        self.budget = budget
        self.done = done or {}
        self.method = method
        self.records: list[dict] = []
        self.points = SimulatedPoints(space)
        self.reused = 0
        self.reuse_limit = budget if reuse else 0
        self.precheck = precheck
        self._kinds: dict[tuple, frozenset[str]] = {}
        self.objective = objective or Objective()
        self.on_refine = on_refine
        self._scheduled = 0  # refinement points of REFINE_AT passed

    # ------------------------------------------------------------------ the objective
    def best(self) -> dict | None:
        """The best call so far under the current objective (None before a valid one)."""
        return self.objective.best(self.records)

    def refine_noise(self) -> bool:
        """Refine the objective's noise from the best call so far; whether it changed (not
        when nothing is estimated, the best call is the one it was refined from, or after
        :data:`MAX_REFINEMENTS`)."""
        best = self.best()
        if (not self.objective.refinable or best is None
                or self.objective.refinement >= MAX_REFINEMENTS
                or best["index"] == self.objective.refined_from
                or self.objective.simulated(best) is None):
            return False
        self.objective = self.objective.refined(best)
        if self.on_refine is not None:
            self.on_refine(self.objective)
        return True

    def refine_if_due(self) -> bool:
        """Refine at each share of the budget in :data:`REFINE_AT` the calls have passed
        since the last check; whether the noise changed."""
        changed = False
        while (self._scheduled < len(REFINE_AT)
               and len(self.records) >= REFINE_AT[self._scheduled] * self.budget):
            self._scheduled += 1
            changed = self.refine_noise() or changed
        return changed

    @property
    def left(self) -> int:
        return self.budget - len(self.records)

    # ------------------------------------------------------------------ what is known
    def simulated(self, action) -> dict | None:
        """The record of the campaign's call of this action's point (None when not simulated)."""
        return self.points.find(self.space.to_values(np.asarray(action, float)))

    def worth_a_call(self, action) -> bool:
        """Whether ``action`` as the next call would simulate something: a point not simulated
        yet, or the very call a resumed journal holds next."""
        journaled = self.done.get(len(self.records))
        return self.simulated(action) is None or (journaled is not None
                                                  and same_action(journaled, action))

    def kinds(self, action) -> frozenset[str]:
        """The kinds of pre-simulation check the point of ``action`` breaks (empty without a
        precheck)."""
        if self.precheck is None:
            return frozenset()
        action = np.asarray(action, float)
        key = tuple(action)
        if key not in self._kinds:  # a base is asked once per finite-difference column
            self._kinds[key] = self.precheck(self.space.to_values(action))
        return self._kinds[key]

    def breaks(self, action, base) -> bool:
        """Whether the point of ``action`` breaks a pre-simulation check that the point of
        ``base`` passes (False without a precheck)."""
        return bool(self.kinds(action) - self.kinds(base))

    # ------------------------------------------------------------------ calls
    def run(self, actions: np.ndarray, lanes: list[int] | None = None,
            phase: str = "explore", phases: list[str] | None = None) -> list[dict]:
        """Evaluate each row of ``actions`` (clipped to [-1, 1]) as one call (``phases``: each
        call's phase, default ``phase`` for all); returns their records in order. When the
        budget ends inside the batch, the calls that fit are made and
        :class:`BudgetExhausted` is raised."""
        actions = np.clip(np.atleast_2d(np.asarray(actions, float)), -1.0, 1.0)
        return self.submit(actions, lanes, phases or [phase] * len(actions))

    def submit(self, actions, lanes: list[int] | None, phases: list[str]) -> list[dict]:
        """The records of ``actions`` (each row a call's action as given; the loop's proposals
        are not clipped here), a point already simulated answered by its record (no call),
        the others evaluated together; :class:`BudgetExhausted` as :meth:`run`. The noise is
        refined when the calls have passed a share of :data:`REFINE_AT` (a method sees it as
        a new :attr:`objective`)."""
        plan = self._plan(actions, lanes, phases)
        batch = replay_or_evaluate(plan.jobs, self.done, self.evaluate_batch, self.method)
        for job, record in zip(plan.jobs, batch):
            self.points.add(job.values, record)
        self.records.extend(batch)
        self.refine_if_due()
        if plan.short:
            raise BudgetExhausted(f"{self.budget} calls spent")
        return [batch[row] if isinstance(row, int) else row for row in plan.rows]

    def _plan(self, actions, lanes: list[int] | None, phases: list[str]) -> _Plan:
        plan = _Plan()
        new = SimulatedPoints(self.space)  # this request's new points -> their job's position
        for i, a in enumerate(actions):
            values = self.space.to_values(np.asarray(a, float))
            index = len(self.records) + len(plan.jobs)
            known = self.points.find(values)
            if known is None:
                known = new.find(values)
            journaled = self.done.get(index)
            if (known is not None and self.reused < self.reuse_limit
                    and not (journaled is not None and same_action(journaled, a))):
                self.reused += 1
                plan.rows.append(known)
                continue
            if index >= self.budget:
                plan.short = True
                break
            new.add(values, len(plan.jobs))
            plan.rows.append(len(plan.jobs))
            plan.jobs.append(Job(index, values, tuple(float(x) for x in a),
                                 lanes[i] if lanes else i, phases[i]))
        return plan
