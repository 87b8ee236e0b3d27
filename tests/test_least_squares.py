"""The one least-squares solver (hmcore.calibration.least_squares and its trust-region
reflective step rule) and the one parameter scaling.

The solvers must propose the very points the implementations they replaced proposed: ``lm``
campaigns are bound to the calls their method made (a resumed campaign replays its journal),
and the diagnosis's recalibrations to theirs. The sequences below were recorded from those
implementations (``lm`` over ``scipy.optimize.least_squares``, the recalibration's own
Levenberg-Marquardt) on a fixed quadratic residual function, before the solver was unified;
``lm``'s were recorded again from its version 3, which ends a stalled descent sooner, and
from its version 5, whose first restart is near the best call (see
test_lm_makes_the_calls_it_made_before). The trust-region solver without checks stays
scipy's, point for point, and the recalibration's sequence is unchanged.
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


# Recorded from lm version 5 (seed 4; W workers, budget B): the phases (e: explore, j: jacobian)
# and the actions of its calls in order. See test_lm_makes_the_calls_it_made_before for how
# they differ from the earlier versions'.
LM_W2_B45 = ('ejjejjejjejjejejejejjejjejejejejjejjejjejejej', [
    (0.0, 0.0), (0.05, 0.0), (0.0, 0.05), (0.2236673797222319, -0.2692962544439388),
    (0.27366737972223193, -0.2692962544439388), (0.2236673797222319, -0.2192962544439388),
    (0.137792893542043, -0.3514928295949189), (0.18779289354204298, -0.3514928295949189),
    (0.137792893542043, -0.3014928295949189), (0.14993997385130228, -0.36373094154262947),
    (0.1999399738513023, -0.36373094154262947), (0.14993997385130228, -0.3137309415426295),
    (0.14623294892930033, -0.3641156405410396), (0.19623294892930032, -0.3641156405410396),
    (0.14900909262983816, -0.3637182046790198), (0.19900909262983818, -0.3637182046790198),
    (0.14970782944822708, -0.36371284103451545), (0.19970782944822707, -0.36371284103451545),
    (0.08476085859013331, -0.3812026707752072), (0.13476085859013331, -0.3812026707752072),
    (0.08476085859013331, -0.3312026707752072), (0.15192228779324826, -0.36636687959551845),
    (0.20192228779324828, -0.36636687959551845), (0.15192228779324826, -0.31636687959551846),
    (0.1456504941574997, -0.36416364823824426), (0.1956504941574997, -0.36416364823824426),
    (0.15059942871736243, -0.3652973972299175), (0.20059942871736242, -0.3652973972299175),
    (0.9524874114154083, -0.8383279522087956), (0.9024874114154082, -0.8383279522087956),
    (-0.014199755607162384, -0.36425126795982266), (0.03580024439283762, -0.36425126795982266),
    (-0.014199755607162384, -0.31425126795982267), (0.15186096980550856, -0.3730042615113035),
    (0.20186096980550855, -0.3730042615113035), (0.15186096980550856, -0.3230042615113035),
    (0.14518941922159717, -0.36434719553081285), (0.19518941922159716, -0.36434719553081285),
    (0.14518941922159717, -0.31434719553081286), (0.14716627840582336, -0.3641475561642598),
    (0.19716627840582335, -0.3641475561642598), (0.6038024139716145, -0.6509443677119431),
    (0.6538024139716145, -0.6509443677119431), (-0.010878804567336614, -0.33955375385494435),
    (0.03912119543266339, -0.33955375385494435),
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

    The pins are version 5's. Version 3 made the same calls up to its first restart (call 19
    with W = 2, call 22 with W = 3), which started anywhere in the box; version 5's first
    restart starts near the best call (calls 19-28 here descend from there), its second
    anywhere (version 4 changed only the residuals' objective, the same as E's on this
    problem). Version 3 against version 2 (the sequences recorded from ``lm`` over
    ``scipy.optimize.least_squares``) made the same calls up to call 17 (W = 2) and call 20
    (W = 3): the first descent has converged at call 9 (sum of squares 0.102) and every trial
    from there is rejected. Version 2 went on, as scipy does, until its step fell below xtol:
    with W = 2, calls 12-33 are 11 rejected trials (each with its speculative Jacobian run),
    each a quarter as far from the converged point as the one before (4e-3 down to 4e-9), then
    it restarted. Version 3 ends a descent at its third rejected trial in a row (calls 12-17;
    with W = 3, 12-20) and restarts at once, from the points version 2 restarted from (the
    generator is drawn the same way: with W = 2, calls 18-28 here are version 2's calls
    34-44). Nothing else differs on this problem: no pre-simulation check is known
    (fake_batch's failures and penalties show only after a run), and no Jacobian run at a
    valid point comes back penalised.
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
