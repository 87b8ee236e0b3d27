"""The default method spends its calls (fake evaluators, no simulator): a finite-difference step
that would break a physics check its base passes goes the other way, a trial that would break
one is not simulated, a Jacobian run broken after its run is redone the other way once; no
point of a campaign is simulated twice (the calls hand back its record), also across a
resume; a descent that stalls or retraces itself ends and lm restarts."""

from __future__ import annotations

import numpy as np
import pytest

from hmcore.calibration.calls import POINT_ATOL, BudgetedCalls, Job
from hmcore.calibration.least_squares import AskTellLeastSquares
from hmcore.calibration.loop import calibrate
from hmcore.calibration.methods import make_proposer
from hmcore.calibration.methods.base import Feedback, Proposal
from hmcore.calibration.methods.lm import NEAR_SCALE, STALL_TRIALS, jacobian_base
from hmcore.model.parameters import Parameter, ParameterSpace
from hmcore.scoring.identifiability import find_stencil

SPACE = ParameterSpace(parameters=(
    Parameter(name="a", kind="multiply", keywords=("PORO",), low=0.5, high=2.0),
    Parameter(name="b", kind="skin", low=-5.0, high=15.0)))
EDGE = 0.4
"""The fake physics check: a point with a > EDGE (action units) breaks the 'trend'."""


def residuals(u) -> np.ndarray:
    """Least squares whose minimum (a = 0.7) lies beyond the check's edge."""
    a, b = u
    return np.array([a - 0.7, 2.0 * (b + 0.3), 0.5 * a * b, 0.3 * (a + b) ** 2])


def action_of(values: dict) -> np.ndarray:
    return SPACE.to_action(values)


def precheck(values: dict) -> frozenset[str]:
    """The kinds of check a point's values break before any run."""
    return frozenset({"poro_perm_trend"}) if action_of(values)[0] > EDGE else frozenset()


def batch_of(log: list | None = None, fails=lambda a: False):
    """An evaluator: the trend check penalises a > EDGE (the record says INVALID, as a
    campaign's does), ``fails(a)`` runs fail; ``log`` collects each job evaluated."""
    def batch(jobs):
        out = []
        for j in jobs:
            if log is not None:
                log.append(j)
            a = np.clip(np.asarray(j.action, float), -1, 1)
            r = residuals(a)
            E = float(r @ r) / r.size
            if fails(a):
                out.append({"index": j.index, "action": list(j.action), "params": j.values,
                            "phase": j.phase, "status": "FAIL", "E": None, "penalty": 10.0,
                            "reward": -10.0})
                continue
            P = 5.0 * (a[0] - EDGE) if a[0] > EDGE else 0.0
            out.append({"index": j.index, "action": list(j.action), "params": j.values,
                        "phase": j.phase, "status": "INVALID" if P else "COMPLETE", "E": E,
                        "penalty": P, "reward": -E - P, "residuals": list(r),
                        "violation_kinds": ["poro_perm_trend"] if P else []})
        return out
    return batch


def broken_jacobian_runs(records: list[dict]) -> list[int]:
    """Jacobian runs penalised where their base passes every check."""
    return [r["index"] for r in records if r["phase"] == "jacobian" and r["status"] == "INVALID"
            and (jacobian_base(r, records) or {}).get("status") == "COMPLETE"]


def distinct(records: list[dict]) -> int:
    u = np.array([action_of(r["params"]) for r in records])
    return sum(1 for i in range(len(u))
               if not any(np.max(np.abs(u[i] - u[j])) <= POINT_ATOL for j in range(i)))


def lm(budget: int, workers: int = 2, check=precheck, log=None, done=None, fails=lambda a: False):
    proposer = make_proposer("lm", SPACE.dim, 4, workers, budget)
    records = calibrate(proposer, SPACE, batch_of(log, fails), budget, workers, done,
                        precheck=check)
    return proposer, records


# ----------------------------------------------------------------------------- (1) the checks
def test_a_finite_difference_step_that_would_break_a_check_goes_the_other_way():
    def breaks(v, u):
        return v[0] > EDGE >= u[0]

    solver = AskTellLeastSquares(2, 0.05, None, None, breaks)
    np.testing.assert_allclose(solver.fd_steps(np.array([0.38, 0.0])), [-0.05, 0.05])
    np.testing.assert_allclose(solver.fd_steps(np.array([0.2, 0.98])), [0.05, -0.05])  # box
    # a base already past the edge steps as before; so does one where both ways break
    np.testing.assert_allclose(solver.fd_steps(np.array([0.5, 0.0])), [0.05, 0.05])
    both = AskTellLeastSquares(2, 0.05, None, None, lambda v, u: v[0] != u[0])
    np.testing.assert_allclose(both.fd_steps(np.array([0.0, 0.0])), [0.05, 0.05])
    # no check known: the steps of before
    np.testing.assert_allclose(AskTellLeastSquares(2, 0.05, None, None).fd_steps(
        np.array([0.38, 0.98])), [0.05, -0.05])


def test_lm_near_a_check_never_simulates_a_run_that_breaks_it():
    """The minimum lies past the check's edge: the descents follow the edge, no Jacobian run
    and no trial crosses it (every call is valid), and the best is at the edge. Without the
    check known beforehand, Jacobian runs at valid points come back penalised."""
    _, records = lm(40)
    assert all(r["status"] == "COMPLETE" for r in records), [
        (r["index"], r["phase"]) for r in records if r["status"] != "COMPLETE"]
    best = min(records, key=lambda r: r["E"])
    assert action_of(best["params"])[0] == pytest.approx(EDGE, abs=0.02)
    _, blind = lm(40, check=None)
    assert broken_jacobian_runs(blind) and not broken_jacobian_runs(records)


def test_a_jacobian_run_broken_after_its_run_is_redone_the_other_way_once():
    """A check nothing predicts (on the simulated responses): the penalised Jacobian run at a
    valid base is run again the other way, once; the descent then uses that column."""
    log: list[Job] = []
    _, records = lm(30, check=None, log=log)
    redone = []
    for r in records:
        base = jacobian_base(r, records)
        if r["phase"] == "jacobian" and r["status"] == "INVALID" and base["status"] == "COMPLETE":
            a = np.asarray(r["action"])
            other = 2 * np.asarray(base["action"]) - a  # the step the other way
            later = [q for q in records[r["index"] + 1:]
                     if np.allclose(q["action"], other, atol=1e-12)]
            assert later and later[0]["phase"] == "jacobian", r["index"]
            redone.append(later[0]["index"])
    assert redone and len(set(redone)) == len(redone)
    assert len(log) == len(records) == 30


def test_a_restart_starts_where_no_check_is_broken():
    proposer = make_proposer("lm", SPACE.dim, 0, 2, 10)
    calls = BudgetedCalls(SPACE, batch_of(), 10, precheck=precheck)
    starts = [proposer._start(calls) for _ in range(30)]
    assert all(s[0] <= EDGE for s in starts)
    free = BudgetedCalls(SPACE, batch_of(), 10)
    again = make_proposer("lm", SPACE.dim, 0, 2, 10)
    assert any(again._start(free)[0] > EDGE for _ in range(30))  # uniform without a check


def test_restarts_alternate_near_the_best_call_and_anywhere_in_the_box():
    """With a best call, the 1st, 3rd, ... restart starts within a few NEAR_SCALE of it (does
    its basin hold a better point?), the 2nd, 4th, ... anywhere (is there another basin?)."""
    calls = BudgetedCalls(SPACE, batch_of(), 10)
    calls.run(np.array([[-0.6, 0.5], [0.9, -0.9]]))
    best = np.asarray(calls.best()["action"])
    proposer = make_proposer("lm", SPACE.dim, 0, 2, 10)
    starts = np.array([proposer._start(calls) for _ in range(40)])
    near = np.abs(starts[0::2] - best).max(axis=1)
    far = np.abs(starts[1::2] - best).max(axis=1)
    assert near.max() < 5 * NEAR_SCALE and np.median(near) < 2 * NEAR_SCALE, near
    assert np.median(far) > 5 * NEAR_SCALE, far  # uniform on [-1, 1]^2: median about 0.9


SPACE5 = ParameterSpace(parameters=tuple(
    Parameter(name=f"m{k}", kind="multiply", keywords=("PORO",), low=0.5, high=2.0)
    for k in range(5)))


def five(u) -> np.ndarray:
    """Five coordinates, curved, the minimum inside the box (not at a call lm would make)."""
    a, b, c, d, e = u
    return np.array([a - 0.3, 2 * (b + 0.4), 3 * a * b + 0.1, a * a - 0.5 * b + 0.05,
                     0.2 * b * b - 0.1, np.sin(2 * c) - 0.3 * d, d * e - 0.2,
                     np.exp(0.5 * e) - 1.2, c + d + e - 0.4, 0.5 * (a - c) ** 2])


def five_batch(jobs):
    out = []
    for j in jobs:
        r = five(np.asarray(j.action, float))
        E = float(r @ r) / r.size
        out.append({"index": j.index, "action": list(j.action), "params": j.values,
                    "phase": j.phase, "status": "COMPLETE", "E": E, "penalty": 0.0,
                    "reward": -E, "residuals": list(r)})
    return out


@pytest.mark.parametrize("budget", [40, 60])
def test_lm_leaves_a_whole_finite_difference_stencil_at_its_best_call(budget):
    """Version 6 computes one Jacobian column anew per accepted step (W = 2), the others are
    secant estimates; a descent that ends on the best call runs the rest there, so the
    report's identifiability finds a whole stencil at the best call itself."""
    proposer = make_proposer("lm", SPACE5.dim, 0, 2, budget)
    records = calibrate(proposer, SPACE5, five_batch, budget, 2)
    assert len(records) == budget
    points = np.array([r["action"] for r in records])
    best = min(range(budget), key=lambda i: records[i]["E"])
    per_step = [r["phase"] for r in records[6:]]  # after the first whole Jacobian
    assert per_step.count("jacobian") < 4 * per_step.count("explore")  # not d per trial
    assert proposer.descents and proposer.descents[0]["x"] is not None  # one ended
    stencil = find_stencil(points, np.ones(budget, bool), best)
    assert stencil is not None and stencil.base == best and stencil.distance == 0.0


# ----------------------------------------------------------------------------- (2) no point twice
def test_a_point_already_simulated_is_answered_from_its_record_without_a_call():
    log: list[Job] = []
    calls = BudgetedCalls(SPACE, batch_of(log), 5)
    first = calls.run(np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 1e-7]]))  # the last: the first
    assert [j.index for j in log] == [0, 1] and first[2] is first[0] and calls.left == 3
    again = calls.run(np.array([[0.1, 0.0], [0.2, 0.0], [0.2, 0.0], [0.0, 1e-5]]))
    assert [j.index for j in log] == [0, 1, 2, 3] and again[0] is first[1]
    assert again[2] is again[1] and calls.reused == 3 and calls.left == 1
    assert [r["index"] for r in calls.records] == [0, 1, 2, 3]


class Repeater:
    """An ask/tell proposer whose every ``every``-th point is the one it asked just before."""

    name = "repeater"

    def __init__(self, every: int):
        self.k = 0
        self.every = every
        self.told: list[float] = []

    def ask(self, n: int) -> list[Proposal]:
        out = []
        for _ in range(n):
            j = self.k - self.k // self.every
            a = np.array([0.04 * j - 0.9, 0.1], np.float32)
            out.append(Proposal(a, np.zeros(3, np.float32), 0, self.k))
            self.k += 1
        return out

    def tell(self, proposals: list[Proposal], feedback: list[Feedback]) -> None:
        self.told += [f.e_obs for f in feedback]

    def recommend(self) -> np.ndarray:
        return np.zeros(2, np.float32)


def test_no_method_simulates_a_point_twice_and_a_resume_replays_exactly():
    log: list[Job] = []
    proposer = Repeater(every=3)
    records = calibrate(proposer, SPACE, batch_of(log), 20, 2)
    assert len(records) == 20 and distinct(records) == 20 and len(log) == 20
    assert proposer.k > 20  # asked more than it was simulated: the repeats cost no call
    for cut in (7, 13):
        log.clear()
        resumed = Repeater(every=3)
        again = calibrate(resumed, SPACE, batch_of(log), 20, 2,
                          {r["index"]: r for r in records[:cut]})
        assert [j.index for j in log] == list(range(cut, 20))
        assert [r["action"] for r in again] == [r["action"] for r in records]
        assert resumed.told == proposer.told


def test_a_journal_that_simulated_a_point_twice_is_replayed_as_it_is():
    """A campaign journaled before points were reused (call 2 simulated call 0's point again)
    resumes without diverging; what is asked after its end is not simulated twice."""
    old = [{"index": i, "action": a, "params": SPACE.to_values(np.array(a)), "phase": "explore",
            "status": "COMPLETE", "E": 1.0, "penalty": 0.0, "reward": -1.0}
           for i, a in enumerate([[0.0, 0.0], [0.1, 0.0], [0.0, 0.0]])]
    log: list[Job] = []
    calls = BudgetedCalls(SPACE, batch_of(log), 6, {r["index"]: r for r in old})
    got = calls.run(np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.0], [0.1, 0.0], [0.3, 0.0]]))
    assert got[:3] == old and got[3] is old[1] and log[0].index == 3
    assert [r["index"] for r in calls.records] == [0, 1, 2, 3]


def test_a_proposer_stuck_on_one_point_still_ends_its_campaign():
    class Stuck(Repeater):
        def ask(self, n):
            return [Proposal(np.zeros(2, np.float32), np.zeros(3, np.float32), 0, 0)
                    for _ in range(n)]

    log: list[Job] = []
    records = calibrate(Stuck(1), SPACE, batch_of(log), 4, 2)
    assert len(records) == 4 and len(log) == 4  # 4 reuses, then simulated again


@pytest.mark.parametrize("check", [precheck, None])
def test_lm_resumes_exactly_with_checks_redone_columns_and_restarts(check):
    """A killed lm campaign resumed from its journal makes the very calls it made, simulating
    only those not journaled: the checks, the redone Jacobian columns, the ended descents and
    the restarts depend only on what was told before, in order."""
    log: list[Job] = []
    proposer, records = lm(40, check=check, log=log)
    assert distinct(records) == len(records) == len(log) == 40
    for cut in (5, 17, 31):
        log.clear()
        again, resumed = lm(40, check=check, log=log,
                            done={r["index"]: r for r in records[:cut]})
        assert [j.index for j in log] == list(range(cut, 40))
        assert [r["action"] for r in resumed] == [r["action"] for r in records]
        assert again.descents == proposer.descents


# ----------------------------------------------------------------------------- (3) restarts
def test_a_descent_that_stalls_ends_and_lm_restarts():
    """From the default start the descent reaches the edge, then its trials gain nothing:
    after STALL_TRIALS of them (or a trial repeating a simulated point) it ends, and the
    calls left go to new descents, not to the same point."""
    proposer, records = lm(60)
    reasons = [d["reason"] for d in proposer.descents]
    assert len(reasons) >= 2, reasons
    assert any(r.startswith(f"{STALL_TRIALS} trials in a row") or "repeats a point" in r
               for r in reasons), reasons
    starts = [r for r in records if r["phase"] == "explore"]
    assert len({tuple(np.round(r["action"], 6)) for r in starts}) == len(starts)


def test_a_failed_start_ends_its_descent_and_the_next_starts_elsewhere():
    proposer, records = lm(20, check=None, fails=lambda a: a[0] > 0.5)
    assert len(records) == 20 and distinct(records) == 20
    assert any(d["reason"] == "the start point failed to simulate" for d in proposer.descents)
