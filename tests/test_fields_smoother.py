"""The ES-MDA update of fields: on a linear-Gaussian problem it samples the Kalman posterior
(Emerick & Reynolds 2013), batching changes nothing, failed members are left out (and too few
stop the iteration naming min_realizations), localisation tapers what a far datum may do.
Pure numpy, no simulator."""

from __future__ import annotations

import numpy as np
import pytest

from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.localisation import distance_taper, gaspari_cohn
from hmcore.fields.smoother import (
    EnsembleSmoother,
    Observations,
    SmootherSettings,
    TooFewRealizations,
    assimilate,
)

ALPHAS = EnsembleSpec().alphas


def linear_problem(seed: int = 0, p: int = 6, o: int = 4):
    """A prior N(m0, C0), data d = G x + e with e ~ N(0, R), and the exact posterior."""
    rng = np.random.default_rng(seed)
    m0 = rng.normal(size=p)
    a = rng.normal(size=(p, p))
    c0 = a @ a.T / p + 0.5 * np.eye(p)
    g = rng.normal(size=(o, p))
    std = rng.uniform(0.2, 0.6, o)
    d = g @ m0 + rng.normal(size=o)
    gain = c0 @ g.T @ np.linalg.inv(g @ c0 @ g.T + np.diag(std ** 2))
    mean = m0 + gain @ (d - g @ m0)
    cov = c0 - gain @ g @ c0
    return m0, c0, g, Observations(d, std), mean, cov


def run(smoother: EnsembleSmoother, g: np.ndarray) -> np.ndarray:
    while not smoother.done:
        index, rows = smoother.ask()
        y = np.full((smoother.ensemble.shape[0], g.shape[0]), np.nan)
        y[index] = rows.astype(np.float64) @ g.T
        smoother.tell(y)
    return smoother.ensemble.astype(np.float64)


def test_a_large_ensemble_samples_the_kalman_posterior_of_a_linear_gaussian_problem():
    m0, c0, g, obs, mean, cov = linear_problem()
    n = 4000
    prior = np.random.default_rng(1).multivariate_normal(m0, c0, size=n)
    post = run(EnsembleSmoother(prior, obs, SmootherSettings(alphas=ALPHAS, seed=2)), g)
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(post.mean(axis=0) - mean) < 0.1 * sd)
    assert np.all(np.abs(post.std(axis=0, ddof=1) / sd - 1.0) < 0.06)
    assert np.abs(np.cov(post.T) - cov).max() < 0.05 * np.abs(cov).max()
    prior_sd = np.sqrt(np.diag(c0))
    assert np.all(sd < prior_sd)  # the data inform every parameter here


def test_batches_of_parameters_give_the_unbatched_update():
    obs = linear_problem(p=40, o=5)[3]
    g = np.random.default_rng(3).normal(size=(5, 40))
    x = np.random.default_rng(4).normal(size=(30, 40)).astype(np.float32)
    y = x.astype(np.float64) @ g.T
    xy = np.column_stack([np.arange(40.0) * 100.0, np.zeros(40)])
    located = Observations(obs.values, obs.std, np.column_stack([np.arange(5) * 800.0,
                                                                 np.zeros(5)]))
    for localisation, radius in (("none", None), ("adaptive", None), ("distance", 1500.0)):
        def update(batch_size, localisation=localisation, radius=radius):
            settings = SmootherSettings(alphas=ALPHAS, localisation=localisation,
                                        radius=radius, seed=5, batch_size=batch_size)
            return assimilate(x, y, located, 1, settings, locations=xy)
        whole, batched = update(None), update(7)
        assert whole.batches == 1 and batched.batches == 6
        np.testing.assert_allclose(batched.ensemble, whole.ensemble, rtol=1e-5, atol=1e-6)
        assert whole.alpha == pytest.approx(3.5) and whole.iteration == 1


def test_failed_members_are_left_out_of_this_update_and_every_later_one():
    m0, c0, g, obs, _, _ = linear_problem()
    x = np.random.default_rng(6).multivariate_normal(m0, c0, size=20).astype(np.float32)
    y = x.astype(np.float64) @ g.T
    failed = np.zeros(20, bool)
    failed[[3, 7]] = True
    y[11] = np.nan  # a member whose responses are not finite counts as failed
    settings = SmootherSettings(alphas=ALPHAS, min_realizations=10, seed=1)
    update = assimilate(x, y, obs, 0, settings, failed=failed)
    assert update.left_out == (3, 7, 11)
    assert update.active.sum() == 17 and not update.active[[3, 7, 11]].any()
    assert np.isnan(update.ensemble[[3, 7, 11]]).all()
    assert np.isfinite(update.ensemble[update.active]).all()
    # what a failed member returned plays no part
    y2 = y.copy()
    y2[[3, 7]] = 1e9
    again = assimilate(x, y2, obs, 0, settings, failed=failed)
    np.testing.assert_array_equal(again.ensemble, update.ensemble)
    # next iteration: the members left out stay out (NaN rows), none newly
    y_next = np.where(np.isnan(update.ensemble[:, :1]), np.nan,
                      update.ensemble.astype(np.float64) @ g.T)
    later = assimilate(update.ensemble, y_next, obs, 1, settings)
    assert later.left_out == () and later.active.sum() == 17


def test_fewer_members_than_min_realizations_stop_with_one_clear_line():
    m0, c0, g, obs, _, _ = linear_problem()
    x = np.random.default_rng(7).multivariate_normal(m0, c0, size=10).astype(np.float32)
    failed = np.arange(10) < 6
    with pytest.raises(TooFewRealizations) as info:
        assimilate(x, x.astype(float) @ g.T, obs, 2,
                   SmootherSettings(alphas=ALPHAS, min_realizations=5), failed=failed)
    message = str(info.value)
    assert "\n" not in message
    assert "assimilation 3 of 3: 4 of 10 members have results (6 failed now" in message
    assert "fewer than min_realizations = 5" in message


def test_a_resumed_iteration_repeats_the_update_exactly():
    m0, c0, g, obs, _, _ = linear_problem()
    x = np.random.default_rng(8).multivariate_normal(m0, c0, size=25).astype(np.float32)
    settings = SmootherSettings.of(EnsembleSpec(size=25, seed=11, localisation="none"))
    first = EnsembleSmoother(x, obs, settings)
    first.tell(x.astype(float) @ g.T)
    x1 = first.ensemble
    second = first.tell(x1.astype(float) @ g.T).ensemble
    resumed = EnsembleSmoother(x1, obs, settings, iteration=1)
    np.testing.assert_array_equal(resumed.tell(x1.astype(float) @ g.T).ensemble, second)
    first.tell(second.astype(float) @ g.T)
    assert first.done
    with pytest.raises(RuntimeError, match="all 3 assimilations are done"):
        first.tell(second.astype(float) @ g.T)


def test_distance_localisation_keeps_far_cells_at_their_prior():
    rng = np.random.default_rng(9)
    n, p = 50, 30
    x = rng.normal(size=(n, p)).astype(np.float32)
    xy = np.column_stack([np.arange(p) * 100.0, np.zeros(p)])
    y = x[:, :1].astype(np.float64) * 2.0  # one datum of the first cell, at x = 0
    obs = Observations(np.array([1.0]), np.array([0.1]), np.array([[0.0, 0.0]]))
    settings = SmootherSettings(alphas=(1.0,), localisation="distance", radius=1000.0)
    update = assimilate(x, y, obs, 0, settings, locations=xy)
    moved = np.abs(update.ensemble - x).max(axis=0)
    assert moved[0] > 0.1 and np.all(moved[10:] == 0)  # 1000 m and beyond: untouched
    plain = assimilate(x, y, obs, 0, SmootherSettings(alphas=(1.0,)))
    assert np.abs(plain.ensemble - x).max(axis=0)[10:].max() > 0  # spurious correlation
    with pytest.raises(ValueError, match="locations"):
        assimilate(x, y, Observations(np.array([1.0]), np.array([0.1])), 0, settings,
                   locations=xy)


@pytest.mark.parametrize("localisation", ["none", "adaptive"])
def test_data_that_do_not_vary_over_the_members_are_left_out_of_the_update(localisation):
    m0, c0, g, obs, _, _ = linear_problem(seed=3)
    prior = np.random.default_rng(4).multivariate_normal(m0, c0, size=60).astype(np.float32)
    y = prior.astype(np.float64) @ g.T
    settings = SmootherSettings(alphas=(1.0,), localisation=localisation, seed=5)
    # a fifth datum that no member moves (a rate the well's control sets), far from its value
    const = Observations(np.append(obs.values, 50.0), np.append(obs.std, 1e-3))
    y5 = np.column_stack([y, np.full(60, 49.0)])
    with np.errstate(all="raise"):  # no 0/0 in the adaptive localisation's correlations
        update = assimilate(prior, y5, const, 0, settings)
    assert update.constant == (4,)
    plain = assimilate(prior, y, obs, 0, settings)
    assert plain.constant == ()
    np.testing.assert_allclose(update.ensemble, plain.ensemble, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="none of the 2 data varies over the 60 members"):
        assimilate(prior, np.ones((60, 2)), Observations(np.zeros(2), np.ones(2)), 0, settings)


def test_the_gaspari_cohn_taper():
    assert gaspari_cohn(np.array([0.0, 2.0, 3.0])).tolist() == [1.0, 0.0, 0.0]
    taper = gaspari_cohn(np.linspace(0, 2, 201))
    assert np.all(np.diff(taper) <= 1e-12)  # falls monotonically from 1 to 0
    assert taper[100] == pytest.approx(5 / 24)  # at r = 1: 1 - 5/3 + 5/8 + 1/2 - 1/4
    rho = distance_taper(np.array([[0.0, 0.0], [np.nan, np.nan]]),
                         np.array([[500.0, 0.0], [3000.0, 0.0], [np.nan, np.nan]]), 1000.0)
    assert rho[0, 0] == pytest.approx(0.2083, abs=1e-3)  # half the radius: r = 1
    assert rho[0, 1] == 0.0 and rho[0, 2] == 1.0 and np.all(rho[1] == 1.0)


def test_bad_inputs_are_refused():
    obs = Observations(np.array([1.0, 2.0]), np.array([0.1, 0.2]))
    x = np.zeros((5, 3), np.float32)
    with pytest.raises(ValueError, match=r"Y must have shape \(members, observations\)"):
        assimilate(x, np.zeros((5, 3)), obs, 0, SmootherSettings(alphas=ALPHAS))
    with pytest.raises(ValueError, match="iteration must lie in 0..2"):
        assimilate(x, np.zeros((5, 2)), obs, 3, SmootherSettings(alphas=ALPHAS))
    with pytest.raises(ValueError, match="std > 0"):
        Observations(np.array([1.0]), np.array([0.0]))


def test_the_layout_stacks_fields_and_scalars_and_splits_them_back():
    from hmcore.fields.grid import FieldGrid
    from hmcore.fields.layout import Layout

    grid = FieldGrid((2, 2, 1), np.array([0, 1, 3]), np.arange(9.0).reshape(3, 3))
    layout = Layout(("poro", "permx"), ("skin",), 3)
    poro, permx = np.ones((4, 3)), np.full((4, 3), 2.0)
    X = layout.stack({"poro": poro, "permx": permx}, {"skin": np.arange(4.0)})
    assert X.shape == (4, 7) and X.dtype == np.float32 and layout.size == 7
    fields, scalars = layout.split(X)
    np.testing.assert_array_equal(fields["permx"], permx)
    np.testing.assert_array_equal(scalars["skin"], np.arange(4.0))
    xy = layout.locations(grid)
    np.testing.assert_array_equal(xy[:3], xy[3:6])
    assert xy.shape == (7, 2) and np.isnan(xy[6]).all()
    with pytest.raises(KeyError, match="no parameter 'ntg'"):
        layout.columns("ntg")
    with pytest.raises(ValueError, match=r"X must have shape \(members, 7\)"):
        layout.split(X[:, :5])
