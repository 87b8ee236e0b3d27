"""Draws from the box-truncated Laplace posterior (``hmcore.calibration.posterior``): the
Gaussian of the linearised fit where the data determine the parameters, uniform across the box
where they do not, inflated by the residuals' mean square when the fit misses the noise, and
never outside the box."""

from __future__ import annotations

import numpy as np
import pytest

from hmcore.calibration.posterior import laplace_draws
from hmcore.model.parameters import Scaling
from hmcore.scoring.identifiability import identifiability, laplace


def _found(J: np.ndarray, r: np.ndarray, best: np.ndarray):
    d = J.shape[1]
    scaling = Scaling(np.zeros(d), np.ones(d), np.zeros(d, bool))
    return identifiability([f"p{k}" for k in range(d)], scaling, best, laplace(J, r))


def test_draws_follow_the_gaussian_of_the_fit_inside_the_box():
    rng = np.random.default_rng(1)
    J = rng.normal(size=(200, 3)) * np.array([40.0, 20.0, 60.0])
    r = rng.normal(size=200) * 0.9  # fits within the noise: no inflation
    found = _found(J, r, np.array([0.1, -0.2, 0.3]))
    draws = laplace_draws(found, 4000, np.random.default_rng(7))
    assert draws.points.shape == (4000, 3) and draws.inflation == 1.0 and draws.free == ()
    assert np.allclose(draws.points.mean(axis=0), [0.1, -0.2, 0.3], atol=3e-3)
    assert np.allclose(np.cov(draws.points.T), found.laplace.covariance, rtol=0.1,
                       atol=2e-6)
    again = laplace_draws(found, 4000, np.random.default_rng(7))
    assert np.array_equal(again.points, draws.points)  # the generator decides, nothing else


def test_a_parameter_the_data_do_not_see_is_drawn_across_the_box():
    rng = np.random.default_rng(2)
    J = np.column_stack([rng.normal(size=100) * 50.0, np.zeros(100)])
    found = _found(J, rng.normal(size=100) * 0.5, np.array([0.0, 0.5]))
    draws = laplace_draws(found, 3000, np.random.default_rng(3))
    assert draws.free == (1,)
    free = draws.points[:, 1]
    assert free.min() < -0.9 and free.max() > 0.9  # the whole box
    assert free.std() == pytest.approx(1 / np.sqrt(3), rel=0.08)  # uniform on [-1, 1]
    assert draws.points[:, 0].std() == pytest.approx(found.laplace.sd[0], rel=0.08)


def test_a_fit_that_misses_the_noise_widens_the_draws_by_its_mean_square():
    rng = np.random.default_rng(4)
    J = rng.normal(size=(300, 2)) * 30.0
    r = rng.normal(size=300) * 3.0  # residuals three times the noise: s2 about 9
    found = _found(J, r, np.zeros(2))
    draws = laplace_draws(found, 4000, np.random.default_rng(5))
    assert draws.inflation == pytest.approx(found.laplace.s2) and draws.inflation > 7
    assert np.allclose(np.cov(draws.points.T), draws.inflation * found.laplace.covariance,
                       rtol=0.12, atol=1e-6)


def test_a_best_call_on_a_bound_keeps_the_half_inside_the_box():
    rng = np.random.default_rng(6)
    J = np.eye(2) * 10.0  # sd 0.1 in each coordinate
    found = _found(J, np.zeros(2), np.array([1.0, 0.0]))
    draws = laplace_draws(found, 1000, np.random.default_rng(8))
    assert len(draws.points) == 1000 and np.all(np.abs(draws.points) <= 1.0)
    assert 0.35 < 1000 / draws.tried < 0.65  # about half fell beyond the bound and were redrawn
    with pytest.raises(ValueError, match="count"):
        laplace_draws(found, -1, rng)
