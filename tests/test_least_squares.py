"""The one least-squares solver (hmcore.calibration.least_squares and its trust-region
reflective step rule) and the one parameter scaling.

The solvers must propose the very points the implementations they replaced proposed: ``lm``
campaigns are bound to the calls their method made (a resumed campaign replays its journal),
and the diagnosis's recalibrations to theirs. The sequences below were recorded from those
implementations (``lm`` over ``scipy.optimize.least_squares``, the recalibration's own
Levenberg-Marquardt) on a fixed quadratic residual function, before the solver was unified;
``lm``'s were recorded again from its version 3, which ends a stalled descent sooner, and
from its versions 5 (the first restart near the best call) and 6 (secant updates of the
Jacobian; see test_lm_makes_the_calls_it_made_before). The trust-region solver without checks
and without ``refresh`` stays scipy's, point for point, and the recalibration's sequence is
unchanged.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from hmcore.calibration.least_squares import fd_jacobian, fd_points, fd_steps
from hmcore.calibration.loop import calibrate
from hmcore.calibration.methods import make_proposer
from hmcore.calibration.trust_region_reflective import TrustRegionReflective
from hmcore.diagnosis.recalibrate import (Coordinates, LevenbergMarquardt, LMSettings, Point,
                                          run_lockstep)
from hmcore.model.parameters import Parameter, ParameterSpace

SPACE = ParameterSpace(parameters=(
    Parameter(name="a", kind="multiply", keywords=("PORO",), low=0.5, high=2.0),
    Parameter(name="b", kind="skin", low=-5.0, high=15.0)))


def residuals(u) -> np.ndarray:
    """A quadratic residual function of two coordinates with a non-zero minimum."""
    a, b = u
    return np.array([a - 0.3, 2.0 * (b + 0.4), 3.0 * a * b + 0.1, a * a - 0.5 * b + 0.05,
                     0.2 * b * b - 0.1])


def fake_batch(jobs):
    """Campaign records of :func:`residuals`; a run with a > 0.5 fails, b < -0.8 is penalised."""
    out = []
    for j in jobs:
        a = np.asarray(j.action)
        fail = bool(a[0] > 0.5)
        r = residuals(a)
        E = float(r @ r) / r.size
        penalty = 10.0 if fail else (0.3 if a[1] < -0.8 else 0.0)
        rec = {"index": j.index, "action": list(j.action), "params": j.values,
               "phase": j.phase, "status": "FAIL" if fail else "COMPLETE",
               "E": None if fail else E, "penalty": penalty,
               "reward": -10.0 if fail else -E - penalty}
        if not fail:
            rec["residuals"] = list(r)
        out.append(rec)
    return out


# Recorded from lm version 6 (seed 4; W workers, budget B): the phases (e: explore, j: jacobian)
# and the actions of its calls in order. See test_lm_makes_the_calls_it_made_before for how
# they differ from the earlier versions'.
LM_W2_B45 = ('ejjejejejejejjejjejejjejejejjejejejejjejejeje', [
    (0.0, 0.0), (0.05, 0.0), (0.0, 0.05), (0.2236673797222319, -0.2692962544439388),
    (0.27366737972223193, -0.2692962544439388), (0.1455916781873478, -0.3502013776581924),
    (0.1455916781873478, -0.30020137765819244), (0.1362518258463292, -0.36515923268081585),
    (0.1862518258463292, -0.36515923268081585), (0.14962715521159686, -0.3603718612255006),
    (0.14962715521159686, -0.3103718612255006), (0.15088880695438003, -0.36340802389570165),
    (0.20088880695438005, -0.36340802389570165), (0.15088880695438003, -0.31340802389570166),
    (0.08570969169321106, -0.3808797531282794), (0.13570969169321107, -0.3808797531282794),
    (0.08570969169321106, -0.3308797531282794), (0.15194390944050684, -0.36630980001315266),
    (0.20194390944050683, -0.36630980001315266), (0.1448724883917369, -0.36710003716254913),
    (0.1448724883917369, -0.31710003716254914), (0.15194390944050684, -0.3163098000131527),
    (0.15048641770440813, -0.36518220752031477), (0.15048641770440813, -0.3151822075203148),
    (0.9524874114154083, -0.8383279522087956), (0.9024874114154082, -0.8383279522087956),
    (-0.013250922504084633, -0.36392835031289483),
    (0.03674907749591537, -0.36392835031289483),
    (-0.013250922504084633, -0.31392835031289484), (0.1520585866445349, -0.3729189295185071),
    (0.2020585866445349, -0.3729189295185071), (0.14282579897322617, -0.37073490492105526),
    (0.14282579897322617, -0.3207349049210553), (0.6038024139716145, -0.6509443677119431),
    (0.6538024139716145, -0.6509443677119431), (-0.009929971464258863, -0.33923083620801653),
    (0.04007002853574114, -0.33923083620801653),
    (-0.009929971464258863, -0.28923083620801654),
    (0.15994967945223698, -0.37098759704180845), (0.20994967945223697, -0.37098759704180845),
    (0.14209997328808688, -0.3694005709735916), (0.14209997328808688, -0.3194005709735916),
    (0.1497909456270737, -0.36392052310859996), (0.19979094562707372, -0.36392052310859996),
    (0.14630993231869996, -0.36390593063241194),
])
LM_W3_B30 = ('ejjejjejjejjejjejjejjejjejjejj', [
    (0.0, 0.0), (0.05, 0.0), (0.0, 0.05), (0.2236673797222319, -0.2692962544439388),
    (0.27366737972223193, -0.2692962544439388), (0.2236673797222319, -0.2192962544439388),
    (0.137792893542043, -0.3514928295949189), (0.18779289354204298, -0.3514928295949189),
    (0.137792893542043, -0.3014928295949189), (0.14993997385130228, -0.36373094154262947),
    (0.1999399738513023, -0.36373094154262947), (0.14993997385130228, -0.3137309415426295),
    (0.14623294892930033, -0.3641156405410396), (0.19623294892930032, -0.3641156405410396),
    (0.14623294892930033, -0.31411564054103963), (0.14900909262983816, -0.3637182046790198),
    (0.19900909262983818, -0.3637182046790198), (0.14900909262983816, -0.3137182046790198),
    (0.14970782944822708, -0.36371284103451545), (0.19970782944822707, -0.36371284103451545),
    (0.14970782944822708, -0.31371284103451547), (0.08476085859013331, -0.3812026707752072),
    (0.13476085859013331, -0.3812026707752072), (0.08476085859013331, -0.3312026707752072),
    (0.15192228779324826, -0.36636687959551845), (0.20192228779324828, -0.36636687959551845),
    (0.15192228779324826, -0.31636687959551846), (0.1456504941574997, -0.36416364823824426),
    (0.1956504941574997, -0.36416364823824426), (0.1456504941574997, -0.3141636482382443),
])

RECALIBRATION = [
    (0, -0.6, 0.7), (0, -0.5, 0.7), (0, -0.6, 0.7999999999999999),
    (1, 0.8500000000000001, -0.9), (1, 0.8, -0.85), (0, -0.09119081092399262, 0.7),
    (0, -0.13282065366657503, 0.7), (1, 0.36603937412679616, -0.47341290983613293),
    (0, -0.029105858392025577, 0.7), (0, -0.02965909064231044, 0.7),
    (1, 0.18546764240144892, -0.41710184787896937),
]


@pytest.mark.parametrize("workers, budget, expected", [(2, 45, LM_W2_B45), (3, 30, LM_W3_B30)])
def test_lm_makes_the_calls_it_made_before(workers, budget, expected):
    """lm's calls, pinned bit for bit (a resumed campaign replays them).

    The pins are version 6's. With W = 3 on these two coordinates version 6 is version 5
    call for call (the two runs beside a trial are the whole Jacobian); with W = 2 its calls
    differ from call 6 on: after an accepted step one column (in turn) is computed anew and
    the other is a secant estimate, where version 5 ran both. Version 5's first restart
    started near the best call (call 19 with W = 2, 22 with W = 3), version 3's anywhere in
    the box (version 4 changed only the residuals' objective, the same as E's on this
    problem). Version 3 against version 2 (the sequences recorded from ``lm`` over
    ``scipy.optimize.least_squares``) made the same calls up to call 17 (W = 2) and call 20
    (W = 3): the first descent has converged at call 9 (sum of squares 0.102) and every trial
    from there is rejected; version 2 went on, as scipy does, until its step fell below xtol,
    version 3 ends a descent at its third rejected trial in a row and restarts.
    """
    phases, actions = expected
    proposer = make_proposer("lm", 2, 4, workers, budget)
    records = calibrate(proposer, SPACE, fake_batch, budget, workers)
    assert "".join(r["phase"][0] for r in records) == phases
    np.testing.assert_allclose([r["action"] for r in records], actions, rtol=0, atol=1e-12)


def test_the_recalibration_asks_the_points_it_asked_before():
    asked = []

    def evaluate(batch):
        asked.extend((k, *u) for k, u in batch)
        return [(residuals(u) if u[1] <= 0.75 else None, None) for _, u in batch]

    u1 = np.array([0.8, -0.9])
    minimisers = [LevenbergMarquardt(np.array([-0.6, 0.7]), LMSettings()),
                  LevenbergMarquardt(u1, LMSettings(trials=1, fd_step=0.05),
                                     start=Point(u1.copy(), residuals(u1)))]
    assert run_lockstep(minimisers, evaluate, workers=3, limit=40) == len(RECALIBRATION)
    assert [k for k, *_ in asked] == [k for k, *_ in RECALIBRATION]
    np.testing.assert_allclose([u for _, *u in asked], [u for _, *u in RECALIBRATION],
                               rtol=0, atol=1e-12)
    assert all(m.reason.startswith("converged") for m in minimisers)


def _scipy_points(fun, x0, fd_step, max_nfev):
    """The points ``scipy.optimize.least_squares`` (trf) evaluates, with this module's
    forward-difference Jacobian, and its result."""
    points, cache = [], {}

    def f(x):
        key = tuple(x)
        if key not in cache:
            points.append(np.array(x, float))
            cache[key] = fun(x)
        return cache[key]

    def jac(x):
        f0 = f(x)
        steps = fd_steps(x, fd_step, 1.0)
        points.extend(fd_points(x, steps))
        return fd_jacobian(f0, [fun(v, fd=True) for v in fd_points(x, steps)], steps)

    res = least_squares(f, x0, jac=jac, bounds=(-1.0, 1.0), method="trf", x_scale=1.0,
                        max_nfev=max_nfev)
    return points, res


def _ask_tell_points(fun, x0, fd_step, max_nfev):
    solver = TrustRegionReflective(x0, fd_step, max_nfev=max_nfev)
    points = []
    while not solver.done:
        asked = solver.ask()
        points += [np.array(u, float) for u in asked]
        solver.tell([(fun(u, fd=solver.jacobian_asked), None) for u in asked])
    return points, solver


def quadratic(u, fd=False):
    return residuals(u)


def rosenbrock(u, fd=False):
    return np.array([10.0 * (u[1] - u[0] ** 2), 1.0 - u[0]])


def pressed(u, fd=False):
    """Its minimum lies outside the box: the bounds are active at the solution."""
    return np.array([u[0] - 1.5, 2.0 * (u[1] + 0.2), u[0] * u[1] - 0.3, np.sin(3.0 * u[2])])


def overflowing(u, fd=False):
    """Its minimum lies at a = 0.95, but trial points beyond a = 0.7 give non-finite residuals
    (scipy shrinks the trust region and tries again); finite differences do not."""
    r = np.array([u[0] - 0.95, 2.0 * (u[1] + 0.3), u[0] * u[1]])
    return np.full_like(r, np.inf) if u[0] > 0.7 and not fd else r


@pytest.mark.parametrize("fun, x0, fd_step, max_nfev", [
    (quadratic, [0.0, 0.0], 0.05, 40), (quadratic, [-0.9, 0.95], 0.1, 40),
    (rosenbrock, [-0.5, 0.9], 0.05, 200), (pressed, [0.2, -0.7, 0.4], 0.05, 60),
    (overflowing, [0.6, -0.9], 0.05, 40), (rosenbrock, [-0.5, 0.9], 0.05, 4),
])
def test_trust_region_reflective_asks_the_points_scipy_evaluates(fun, x0, fd_step, max_nfev):
    expected, res = _scipy_points(fun, np.array(x0), fd_step, max_nfev)
    points, solver = _ask_tell_points(fun, np.array(x0), fd_step, max_nfev)
    assert len(points) == len(expected)
    np.testing.assert_allclose(points, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(solver.x, res.x, rtol=0, atol=1e-12)
    assert solver.status == res.status and solver.cost == pytest.approx(res.cost, abs=1e-12)


def test_a_failed_run_ends_a_descent_and_leaves_a_jacobian_column_at_zero():
    solver = TrustRegionReflective(np.array([0.0, 0.98]), 0.05)
    (x0,) = solver.ask()
    solver.tell([(residuals(x0), None)])
    assert solver.jacobian_asked
    fd = solver.ask()
    np.testing.assert_allclose(fd, [[0.05, 0.98], [0.0, 0.93]])  # b steps down at the bound
    solver.tell([(residuals(fd[0]), None), (None, None)])
    assert not solver.J[:, 1].any() and solver.J[:, 0].any()
    assert len(solver.ask()) == 1  # a trial point
    solver.tell([(None, None)])
    assert solver.done and solver.failed and solver.ask() == []


def five(u, fd=False):
    """Five coordinates, ten residuals, curved in all of them; its minimum inside the box."""
    a, b, c, d, e = u
    return np.array([a - 0.3, 2 * (b + 0.4), 3 * a * b + 0.1, a * a - 0.5 * b + 0.05,
                     0.2 * b * b - 0.1, np.sin(2 * c) - 0.3 * d, d * e - 0.2,
                     np.exp(0.5 * e) - 1.2, c + d + e - 0.4, 0.5 * (a - c) ** 2])


def test_with_refresh_an_accepted_step_is_a_secant_update_then_its_columns_in_turn():
    """After an accepted trial one column, the next in turn, is asked anew at the new point
    and replaces the secant estimate there; the others stay as the update left them. A
    trial rejected while columns are secant estimates asks those columns, at the same point."""
    solver = TrustRegionReflective(np.zeros(5), 0.05, refresh=1)
    (x0,) = solver.ask()
    solver.tell([(five(x0), None)])
    assert solver.columns_asked == [0, 1, 2, 3, 4]  # a descent starts on a whole Jacobian
    assert solver.refresh_columns(1) == [0]
    solver.tell([(five(u), None) for u in solver.ask()])
    at = solver.x.copy()  # where the last finite differences were
    turns, rejected = [], 0
    while len(turns) < 6 and not solver.done:
        asked = solver.ask()
        if not solver.jacobian_asked:  # a trial
            solver.tell([(five(asked[0]), None)])
            continue
        stale = solver.J.copy()
        if np.array_equal(solver.x, at):  # after a rejected trial: the secant columns anew
            assert solver.columns_asked == [int(i) for i in np.flatnonzero(~solver.fresh)]
            rejected += 1
        else:
            assert len(solver.columns_asked) == 1 and not solver.fresh.any()
            turns.append(solver.columns_asked[0])
        columns = solver.columns_asked
        solver.tell([(five(u), None) for u in asked])
        at = solver.x.copy()
        assert solver.fresh[columns].all()
        others = [i for i in range(5) if i not in columns]
        np.testing.assert_array_equal(solver.J[:, others], stale[:, others])
        steps = solver.fd_steps(solver.x)[columns]
        np.testing.assert_allclose(solver.J[:, columns],
                                   np.array([(five(u) - solver.f) for u in asked]).T / steps)
    assert turns[:5] == [0, 1, 2, 3, 4], (turns, rejected)


def test_the_secant_update_maps_the_step_to_the_change_of_the_residuals():
    solver = TrustRegionReflective(np.zeros(5), 0.05, refresh=1)
    (x0,) = solver.ask()
    solver.tell([(five(x0), None)])
    solver.tell([(five(u), None) for u in solver.ask()])
    J0, x0, f0 = solver.J.copy(), solver.x.copy(), solver.f.copy()
    (trial,) = solver.ask()
    solver.tell([(five(trial), None)])
    assert solver.jacobian_asked and not np.array_equal(solver.x, x0)  # accepted
    step, change = solver.x - x0, solver.f - f0
    np.testing.assert_allclose(solver.J @ step, change, rtol=1e-10, atol=1e-12)
    # the least change that does so: J0 moved along the step only
    np.testing.assert_allclose((solver.J - J0) @ np.linalg.svd(step[None])[2][1:].T, 0,
                               atol=1e-12)


def test_a_trial_rejected_on_secant_columns_asks_those_anew_before_the_next_trial():
    solver = TrustRegionReflective(np.zeros(2), 0.05, refresh=1)
    (x0,) = solver.ask()
    solver.tell([(quadratic(x0), None)])
    solver.tell([(quadratic(u), None) for u in solver.ask()])
    (trial,) = solver.ask()
    solver.tell([(quadratic(trial), None)])  # accepted: column 0 asked anew, 1 a secant
    solver.tell([(quadratic(u), None) for u in solver.ask()])
    assert list(solver.fresh) == [True, False]
    x = solver.x.copy()
    (trial,) = solver.ask()
    solver.tell([(quadratic(trial) + 10.0, None)])  # worse: rejected
    assert solver.jacobian_asked and solver.columns_asked == [1]
    np.testing.assert_array_equal(solver.x, x)
    np.testing.assert_allclose(solver.ask(), [x + [0.0, solver.fd_steps(x)[1]]])


def test_complete_asks_the_secant_columns_at_the_end_point_and_ends_on_a_whole_jacobian():
    solver = TrustRegionReflective(np.zeros(5), 0.05, refresh=1)
    assert not solver.complete()  # no Jacobian yet: nothing to complete
    (x0,) = solver.ask()
    solver.tell([(five(x0), None)])
    solver.tell([(five(u), None) for u in solver.ask()])
    assert not solver.complete()  # every column a finite difference at x
    while solver.fresh.all():  # until an accepted step leaves secant columns
        asked = solver.ask()
        solver.tell([(five(u, fd=solver.jacobian_asked), None) for u in asked])
    solver.tell([(five(u), None) for u in solver.ask()])  # its one column anew
    stale = [int(k) for k in np.flatnonzero(~solver.fresh)]
    assert len(stale) == 4 and solver.complete()
    assert solver.jacobian_asked and solver.columns_asked == stale and not solver.done
    asked = solver.ask()
    solver.tell([(five(u), None) for u in asked])
    assert solver.done and solver.fresh.all() and solver.ask() == []
    steps = solver.fd_steps(solver.x)
    whole = np.array([(five(u) - solver.f) / h
                      for u, h in zip(solver.fd_points(solver.x), steps)]).T
    np.testing.assert_allclose(solver.J, whole)


@pytest.mark.parametrize("fun, x0", [(rosenbrock, [-0.5, 0.9]), (pressed, [0.2, -0.7, 0.4]),
                                     (five, [0.8, -0.8, 0.5, 0.5, -0.9])])
def test_secant_updates_reach_scipys_minimum_in_fewer_runs(fun, x0):
    """The runs (trials and finite differences) until the cost is within 1 % of the
    minimum scipy finds, with a whole Jacobian at every accepted point against one column."""
    def runs_to_minimum(refresh):
        solver = TrustRegionReflective(np.array(x0, float), 0.05, max_nfev=400,
                                       refresh=refresh)
        n, costs = 0, []
        while not solver.done:
            asked = solver.ask()
            n += len(asked)
            solver.tell([(fun(u, fd=solver.jacobian_asked), None) for u in asked])
            costs.append((n, solver.cost))
        return costs

    whole, secant = runs_to_minimum(None), runs_to_minimum(1)
    best = min(c for _, c in whole)
    assert min(c for _, c in secant) <= 1.01 * best + 1e-6
    first = [next(n for n, c in costs if c <= 1.01 * best + 1e-6) for costs in (whole, secant)]
    assert first[1] < first[0], first


# ----------------------------------------------------------------------------- scaling
def test_a_log_scaled_parameter_maps_equal_steps_to_equal_ratios():
    log_a = Parameter(name="a", kind="multiply", keywords=("PORO",), low=0.25, high=4.0, log=True)
    space = ParameterSpace(parameters=(log_a, SPACE.parameters[1]))
    values = space.to_values(np.array([0.0, 0.0]))
    assert values["a"] == pytest.approx(1.0) and values["b"] == pytest.approx(5.0)
    assert space.to_values(np.array([-1.0, 1.0])) == pytest.approx({"a": 0.25, "b": 15.0})
    assert space.to_values(np.array([0.5, 0.0]))["a"] == pytest.approx(2.0)
    np.testing.assert_allclose(space.to_action({"a": 2.0, "b": 0.0}), [0.5, -0.5])
    with pytest.raises(ValueError, match="log scale needs low > 0"):
        Parameter(name="s", kind="skin", low=-5.0, high=15.0, log=True)


def test_without_the_flag_actions_map_linearly_as_before_and_dumps_are_unchanged():
    a = np.random.default_rng(0).uniform(-1.2, 1.2, (50, 2))
    low, high = SPACE.low, SPACE.high
    for action in a:
        x = low + (np.clip(action, -1, 1) + 1.0) * 0.5 * (high - low)
        assert list(SPACE.to_values(action).values()) == list(x)  # bit for bit
    assert "log" not in SPACE.parameters[0].model_dump()
    assert Parameter.model_validate(SPACE.parameters[0].model_dump()).log is False


def test_the_recalibration_scales_every_factor_in_log_and_honours_the_flag():
    skin_log = Parameter(name="s", kind="skin", low=0.5, high=8.0, log=True)
    coords = Coordinates([*SPACE.parameters, skin_log])
    assert coords.log.tolist() == [True, False, True]
    values = coords.to_values(np.zeros(3))
    assert values == pytest.approx({"a": 1.0, "b": 5.0, "s": 2.0})
    np.testing.assert_allclose(coords.to_u(values), 0.0, atol=1e-15)
