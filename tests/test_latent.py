"""Latent actions (issue 42): the prior ensemble's leading modes as calibration parameters
(hmcore.fields.latent), the prior as regularisation in the objective, and the simulator that
runs a call's fields (hmcore.fields.members.LatentSimulator). No simulator here: a fake one
records the deck it is given."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmcore.calibration.objective import Objective
from hmcore.fields.grdecl import read_grdecl
from hmcore.fields.latent import PREFIX, LatentBasis, LatentSpec, prior_residuals
from hmcore.fields.layout import Layout
from hmcore.fields.members import INCLUDE_NAME, LatentSimulator, ensemble_table
from hmcore.fields.spec import FieldSpec
from hmcore.fields.transform import to_physical
from hmcore.reporting.identifiability import assess


def correlated_ensemble(rng: np.random.Generator, members: int = 40, p: int = 300,
                        rank: int = 6) -> np.ndarray:
    """Members of a field whose spread lies mostly in ``rank`` directions, plus a little
    noise: ``(members, p)``."""
    directions = rng.normal(size=(rank, p)) * np.linspace(3.0, 0.5, rank)[:, None]
    return 2.0 + rng.normal(size=(members, rank)) @ directions + 0.01 * rng.normal(
        size=(members, p))


def test_the_modes_hold_the_share_asked_with_the_fewest_modes():
    X = correlated_ensemble(np.random.default_rng(1))
    basis = LatentBasis.of_ensemble(X, share=0.9)
    A = (X - X.mean(axis=0)) / np.sqrt(len(X) - 1)
    s2 = np.linalg.svd(A, compute_uv=False) ** 2
    held = np.cumsum(s2) / s2.sum()
    assert basis.k == int(np.argmax(held >= 0.9)) + 1
    assert basis.share == pytest.approx(held[basis.k - 1], rel=1e-9)
    assert basis.share >= 0.9 and (basis.k == 1 or held[basis.k - 2] < 0.9)
    assert basis.available == len(X) - 1  # the centred members span N - 1 directions
    np.testing.assert_allclose(np.sort(np.einsum("ij,ij->i", basis.modes, basis.modes))[::-1],
                               s2[:basis.k], rtol=1e-8)


def test_the_modes_are_orthogonal_and_max_modes_caps_them():
    X = correlated_ensemble(np.random.default_rng(2))
    basis = LatentBasis.of_ensemble(X, share=1.0, max_modes=3)
    assert basis.k == 3 and basis.names == ("mode_01", "mode_02", "mode_03")
    gram = basis.modes @ basis.modes.T
    np.testing.assert_allclose(gram - np.diag(np.diag(gram)), 0.0, atol=1e-8 * gram.max())


def test_standard_normal_coefficients_give_the_prior_mean_and_covariance():
    """z ~ N(0, I) through every mode reproduces the ensemble's mean and covariance."""
    X = correlated_ensemble(np.random.default_rng(3), members=30, p=50)
    basis = LatentBasis.of_ensemble(X, share=1.0)
    cov = basis.modes.T @ basis.modes  # E[(M^T z)(M^T z)^T] for z ~ N(0, I)
    np.testing.assert_allclose(cov, np.cov(X, rowvar=False), atol=1e-9)
    np.testing.assert_allclose(basis.fields(np.zeros(basis.k)), X.mean(axis=0))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_projecting_a_basis_field_gives_back_its_coefficients(seed):
    rng = np.random.default_rng(seed)
    basis = LatentBasis.of_ensemble(correlated_ensemble(rng, members=20, p=80), share=0.95)
    z = rng.normal(size=basis.k)
    np.testing.assert_allclose(basis.project(basis.fields(z)), z, atol=1e-7)


def test_a_member_outside_the_span_projects_to_its_nearest_field():
    X = correlated_ensemble(np.random.default_rng(4))
    basis = LatentBasis.of_ensemble(X, share=0.99)
    x = X[0] + np.random.default_rng(5).normal(size=X.shape[1])
    z = basis.project(x)
    best = np.linalg.lstsq(basis.modes.T, x - basis.mean, rcond=None)[0]
    np.testing.assert_allclose(z, best, atol=1e-8)


def test_an_ensemble_without_spread_or_with_a_nan_is_refused():
    with pytest.raises(ValueError, match="no spread"):
        LatentBasis.of_ensemble(np.ones((5, 10)))
    X = np.random.default_rng(0).normal(size=(5, 10))
    X[2, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        LatentBasis.of_ensemble(X)


def test_the_basis_table_round_trips():
    X = correlated_ensemble(np.random.default_rng(6), p=20)
    basis = LatentBasis.of_ensemble(X, share=0.9)
    rows = pd.DataFrame({"parameter": ["f"] * 20, "cell": np.arange(20)})
    back = LatentBasis.from_table(basis.table(rows), basis.share, basis.available)
    np.testing.assert_array_equal(back.modes, basis.modes)
    np.testing.assert_array_equal(back.mean, basis.mean)
    assert back.names == basis.names


@pytest.mark.parametrize("keys, rule", [({"share": 0.0}, "greater than 0"),
                                        ({"share": 1.5}, "less than or equal to 1"),
                                        ({"bound": -1.0}, "greater than 0"),
                                        ({"prior": "flat"}, "regularised"),
                                        ({"modes": 5}, "Extra inputs")])
def test_a_bad_latent_section_states_the_rule(keys, rule):
    with pytest.raises(ValueError, match=rule):
        LatentSpec(**keys)


# ----------------------------------------------------------------------------- the objective
class _Rows:
    """The part of an ObservationSet the likelihood reads: 3 fitted rows, white, sigma 1."""

    def __init__(self):
        self.rows = pd.DataFrame({"observed": [1.0, 2.0, 3.0], "sigma": [1.0, 1.0, 1.0],
                                  "period": ["fit"] * 3, "sigma_source": ["given"] * 3})

    def whiten(self, r, period):
        return np.asarray(r, float)

    def n_noise(self, period):
        return 3


def record(z: list[float], simulated=(1.5, 2.0, 2.0)) -> dict:
    params = {f"{PREFIX}{i + 1:02d}": v for i, v in enumerate(z)}
    return {"status": "COMPLETE", "E": 0.1, "penalty": 0.0, "reward": -0.1,
            "params": {**params, "skin": 3.0}, "simulated": list(simulated)}


def test_the_regularised_likelihood_adds_the_coefficients_squares():
    rows = _Rows()
    plain = Objective("likelihood", rows)
    prior = Objective("likelihood", rows, prior=("mode_01", "mode_02"))
    r = record([1.0, -2.0])
    chi2 = 0.5 ** 2 + 0.0 + 1.0 ** 2
    assert plain.likelihood(r) == pytest.approx(chi2 / 3)
    assert prior.likelihood(r) == pytest.approx((chi2 + 1.0 + 4.0) / 3)
    np.testing.assert_allclose(prior.residuals(r), [0.5, 0.0, -1.0, 1.0, -2.0, 0.0])
    assert prior.best([record([2.0, 2.0]), record([0.0, 0.0], (1.6, 2.0, 2.0))]) is not None
    # the smaller coefficients win where the misfits are close
    best = prior.best([record([2.0, 2.0]), record([0.0, 0.0], (1.6, 2.0, 2.0))])
    assert best["params"]["mode_01"] == 0.0


def test_prior_residuals_are_the_coefficients_in_order():
    np.testing.assert_array_equal(prior_residuals({"b": 2.0, "a": 1.0}, ("a", "b")), [1.0, 2.0])
    assert np.isnan(prior_residuals({}, ("a",))).all()


# ----------------------------------------------------------------------------- the run
class _Recorder:
    name = "fake"

    def __init__(self):
        self.decks: list[str] = []

    def run(self, deck: Path, run_dir: Path):
        self.decks.append(Path(deck).read_text())
        return "ran"


class _Grid:
    """The part of a FieldGrid write_member reads: 6 active cells of 8."""

    n_active = 6
    active = np.array([1, 1, 0, 1, 1, 1, 0, 1], bool)

    def full(self, values, fill=0.0):
        out = np.full(8, fill, float)
        out[self.active] = values
        return out


def test_the_latent_simulator_runs_the_fields_of_the_calls_coefficients(tmp_path):
    poro = FieldSpec.model_validate({"name": "poro", "kind": "field", "keyword": "PORO",
                                     "low": 0.01, "high": 0.4,
                                     "prior": {"source": "files", "folder": "x"}})
    layout = Layout(("poro",), (), 6)
    rng = np.random.default_rng(7)
    X = 0.2 + 0.03 * rng.normal(size=(12, 6))
    basis = LatentBasis.of_ensemble(X, share=0.95)
    rows = ensemble_table(X[:1].astype(np.float32), layout)[["parameter", "cell"]]
    path = tmp_path / "basis.parquet"
    basis.table(rows).to_parquet(path)
    deck = tmp_path / "RUN.DATA"
    deck.write_text("RUNSPEC\nGRID\nPORO\n 8*0.2 /\nPROPS\n")
    inner = _Recorder()
    z = rng.normal(size=basis.k)
    sim = LatentSimulator(inner, path, (poro,), _Grid(), layout, frozenset({"PORO"})).bound(z)
    assert sim.run(deck, tmp_path / "run") == "ran"
    written = read_grdecl(tmp_path / "run" / INCLUDE_NAME)["PORO"]
    expected = _Grid().full(to_physical(basis.fields(z), poro))
    np.testing.assert_allclose(written, expected, rtol=1e-6)
    assert inner.decks[0].index("INCLUDE") < inner.decks[0].index("PROPS")


def test_the_sign_of_each_mode_is_fixed_by_its_largest_entry():
    X = correlated_ensemble(np.random.default_rng(8))
    basis = LatentBasis.of_ensemble(X, share=0.95)
    top = np.abs(basis.modes).argmax(axis=1)
    assert (basis.modes[np.arange(basis.k), top] > 0).all()
    again = LatentBasis.of_ensemble(X[::-1].copy(), share=0.95)  # the members in another order
    np.testing.assert_allclose(again.modes, basis.modes, atol=1e-9 * np.abs(basis.modes).max())


def test_the_prior_determines_a_coefficient_the_data_leave_free():
    """The identifiability (and the Laplace draws on it) of a latent campaign stand on the
    posterior the objective minimises: with the prior's rows, a coefficient no datum moves
    has the prior's 95 % interval, +-1.96, not the whole box."""
    parameters = [{"name": n, "kind": "latent", "low": -3.0, "high": 3.0}
                  for n in ("mode_01", "mode_02")]
    base, h = np.array([0.1, 0.0]), 0.01

    def rec(index: int, a: np.ndarray) -> dict:
        z = 3.0 * a
        return {"index": index, "action": list(a), "status": "COMPLETE",
                "residuals": [20.0 * (a[0] - 0.1), 5.0 * (a[0] - 0.1)],
                "params": {"mode_01": z[0], "mode_02": z[1]}}

    records = [rec(0, base), rec(1, base + [h, 0.0]), rec(2, base + [0.0, h])]
    free = assess(records, parameters, 0, None)
    held = assess(records, parameters, 0, None, prior=("mode_01", "mode_02"))
    assert 1 in free.result.uninformed and free.result.share[1] == pytest.approx(1.0)
    assert held.result.low[1] == pytest.approx(-1.96, abs=0.01)
    assert held.result.high[1] == pytest.approx(1.96, abs=0.01)
    assert held.result.high[0] - held.result.low[0] < free.result.high[0] - free.result.low[0]
