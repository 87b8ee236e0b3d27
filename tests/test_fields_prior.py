"""Prior fields drawn by hmflow: reproducible for a seed, honouring each layer's mean and
standard deviation, the stated porosity-permeability relation and the variogram; zones checked
against the grid. A small block-centred grid built in numpy, no deck, no simulator."""

from __future__ import annotations

import math

import numpy as np
import pytest

import hmcore.fields.prior as prior_module
from hmcore.fields.covariance import covariance_model, practical_range
from hmcore.fields.grid import FieldGrid
from hmcore.fields.prior import draw_prior
from hmcore.fields.spec import FieldSpec, Variogram
from hmcore.fields.zones import prior_problems

NX, NY, NZ, DX = 16, 12, 3, 100.0


def small_grid(inactive: tuple[int, ...] = (0, 1, 17)) -> FieldGrid:
    """16 x 12 x 3 cells of 100 m x 100 m, 5 m thick, a few inactive; FIPNUM 1 west, 2 east."""
    total = NX * NY * NZ
    active = np.setdiff1d(np.arange(total), inactive)
    i, j, k = active % NX, (active // NX) % NY, active // (NX * NY)
    centres = np.column_stack([(i + 0.5) * DX, (j + 0.5) * DX, 2000.0 + 5.0 * k + 2.5])
    values = {"PORO": np.full(active.size, 0.2), "PERMX": np.full(active.size, 100.0),
              "PERMZ": np.full(active.size, 10.0)}
    regions = {"FIPNUM": np.where(i < NX // 2, 1, 2)}
    return FieldGrid((NX, NY, NZ), active, centres, values, regions, "small")


GRID = small_grid()
LAYERS = ((1, 0.25, 0.04), (2, 0.10, 0.02), (3, 0.20, 0.03))


def poro(seed=1, variogram=None, azimuth=90.0) -> FieldSpec:
    v = variogram or {"model": "spherical", "ranges": [800.0, 300.0, 10.0], "azimuth": azimuth}
    return FieldSpec.model_validate({
        "name": "poro", "keyword": "PORO",
        "prior": {"source": "geostatistical", "seed": seed, "variogram": v,
                  "zones": [{"layers": [k, k], "mean": m, "std": s} for k, m, s in LAYERS]}})


def permx(scatter=0.25, seed=2) -> FieldSpec:
    return FieldSpec.model_validate({
        "name": "permx", "keyword": "PERMX", "copies": ["PERMY"],
        "prior": {"source": "relation", "from": "poro", "intercept": 0.77, "slope": 9.02,
                  "scatter": scatter, "seed": seed}})


def test_draws_are_reproducible_for_a_seed_and_independent_of_the_ensemble_size():
    a = draw_prior([poro(), permx()], GRID, 6)
    b = draw_prior([poro(), permx()], GRID, 6)
    assert a.values["poro"].dtype == np.float32 and a.values["poro"].shape == (6, GRID.n_active)
    for name in ("poro", "permx"):
        np.testing.assert_array_equal(a.values[name], b.values[name])
    assert a.seeds == {"poro": 1, "permx": 2}
    small = draw_prior([poro(), permx()], GRID, 3)
    np.testing.assert_array_equal(small.values["permx"], a.values["permx"][:3])
    later = draw_prior([poro(), permx()], GRID, 2, start=4)
    np.testing.assert_array_equal(later.values["poro"], a.values["poro"][4:6])
    other = draw_prior([poro(seed=9), permx()], GRID, 6)
    assert not np.allclose(other.values["poro"], a.values["poro"])


def test_each_layer_has_its_mean_and_standard_deviation_within_sampling_error():
    n = 300
    draw = draw_prior([poro()], GRID, n).values["poro"].astype(float)
    k = GRID.ijk[:, 2]
    for layer, mean, std in LAYERS:
        cells = draw[:, k == layer]
        member_means = cells.mean(axis=1)  # the members' layer means: independent draws
        assert abs(member_means.mean() - mean) < 4 * member_means.std() / math.sqrt(n)
        assert cells.std() == pytest.approx(std, rel=0.08)


def test_the_relation_gives_the_stated_porosity_permeability_correlation():
    n = 200
    draw = draw_prior([poro(), permx(scatter=0.25)], GRID, n)
    phi = draw.values["poro"].astype(float)
    logk = draw.values["permx"].astype(float)
    residual = logk - (0.77 + 9.02 * phi)
    assert residual.mean() == pytest.approx(0.0, abs=0.03)
    assert residual.std() == pytest.approx(0.25, rel=0.05)
    k = GRID.ijk[:, 2]
    for layer, _, std in LAYERS:
        expected = 9.02 * std / math.hypot(9.02 * std, 0.25)
        found = np.corrcoef(phi[:, k == layer].ravel(), logk[:, k == layer].ravel())[0, 1]
        assert found == pytest.approx(expected, abs=0.03)


def test_cosimulation_gives_the_stated_correlation_and_the_target_s_moments():
    n = 200
    cosim = FieldSpec.model_validate({
        "name": "permx", "keyword": "PERMX",
        "prior": {"source": "cosimulation", "from": "poro", "correlation": 0.7, "seed": 5,
                  "zones": [{"layers": [1, 3], "mean": 2.0, "std": 0.5}]}})
    draw = draw_prior([poro(), cosim], GRID, n)
    z = draw.scores["poro"].astype(float).ravel()
    found = np.corrcoef(z, draw.scores["permx"].astype(float).ravel())[0, 1]
    assert found == pytest.approx(0.7, abs=0.03)
    assert draw.values["permx"].mean() == pytest.approx(2.0, abs=0.05)
    assert draw.values["permx"].std() == pytest.approx(0.5, rel=0.08)


def test_the_correlation_at_a_lag_is_the_variogram_s_along_and_across_the_major_axis():
    n = 400
    variogram = {"model": "exponential", "ranges": [900.0, 300.0, 10.0], "azimuth": 90.0}
    z = draw_prior([poro(variogram=variogram)], GRID, n).scores["poro"].astype(float)
    ijk = GRID.ijk
    index = {tuple(c): m for m, c in enumerate(ijk.tolist())}

    def lag_correlation(di: int, dj: int) -> float:
        pairs = [(m, index[(i + di, j + dj, k)]) for (i, j, k), m in index.items()
                 if (i + di, j + dj, k) in index]
        a, b = np.array(pairs).T
        return float(np.corrcoef(z[:, a].ravel(), z[:, b].ravel())[0, 1])

    # azimuth 90: the major axis along x (i); practical range 900 m along it, 300 m across
    assert lag_correlation(3, 0) == pytest.approx(math.exp(-3 * 300 / 900), abs=0.06)
    assert lag_correlation(0, 1) == pytest.approx(math.exp(-3 * 100 / 300), abs=0.06)
    assert lag_correlation(0, 3) == pytest.approx(math.exp(-3 * 300 / 300), abs=0.06)


def test_practical_ranges_put_five_percent_correlation_at_the_range():
    for model in ("gaussian", "exponential", "matern"):
        v = Variogram(model=model, ranges=(1000.0, 1000.0, 1000.0), azimuth=0.0)
        m = covariance_model(v, 0.0)
        assert m.correlation(1000.0) == pytest.approx(0.05, abs=1e-6)
    assert practical_range("spherical") == 1.0
    sph = covariance_model(Variogram(model="spherical", ranges=(700.0, 700.0, 7.0)), 0.0)
    assert sph.correlation(700.0) == pytest.approx(0.0, abs=1e-12)


def test_a_drawn_azimuth_is_recorded_per_member_and_shared_by_the_family():
    variogram = {"model": "spherical", "ranges": [800.0, 300.0, 10.0], "azimuth": [110.0, 170.0]}
    draw = draw_prior([poro(variogram=variogram), permx()], GRID, 5)
    az = draw.azimuths["poro"]
    assert az.shape == (5, 3) and np.all((az >= 110) & (az <= 170)) and len(np.unique(az)) == 15
    np.testing.assert_array_equal(draw.azimuths["permx"], az)


def test_region_zones_and_given_members():
    regional = FieldSpec.model_validate({
        "name": "ntg", "keyword": "PORO",
        "prior": {"source": "geostatistical", "seed": 4,
                  "variogram": {"model": "gaussian", "ranges": [500.0, 500.0, 5.0]},
                  "zones": [{"region": "FIPNUM", "number": 1, "mean": 0.1, "std": 0.01},
                            {"region": "FIPNUM", "number": 2, "mean": 0.3, "std": 0.01}]}})
    values = draw_prior([regional], GRID, 20).values["ntg"]
    west = GRID.regions["FIPNUM"] == 1
    assert values[:, west].mean() == pytest.approx(0.1, abs=0.01)
    assert values[:, ~west].mean() == pytest.approx(0.3, abs=0.01)
    files = FieldSpec.model_validate({"name": "k", "keyword": "PERMX",
                                      "prior": {"source": "files", "folder": "x"}})
    given = np.full((2, GRID.n_active), 2.0)
    assert draw_prior([files], GRID, 2, given={"k": given}).values["k"].dtype == np.float32
    with pytest.raises(ValueError, match="pass them as given"):
        draw_prior([files], GRID, 2)


def test_a_large_zone_is_drawn_by_gstools_randomisation_method(monkeypatch):
    monkeypatch.setattr(prior_module, "EXACT_LIMIT", 10)
    one_zone = FieldSpec.model_validate({
        "name": "poro", "keyword": "PORO",
        "prior": {"source": "geostatistical", "seed": 3,
                  "variogram": {"model": "gaussian", "ranges": [600.0, 600.0, 10.0]},
                  "zones": [{"layers": [1, 3], "mean": 0.2, "std": 0.05}]}})
    draw = draw_prior([one_zone], GRID, 1).values["poro"]
    assert np.isfinite(draw).all() and 0.01 < draw.std() < 0.1
    np.testing.assert_array_equal(draw, draw_prior([one_zone], GRID, 1).values["poro"])


def test_zone_problems_are_all_reported_against_the_grid():
    bad = FieldSpec.model_validate({
        "name": "ntg", "keyword": "NTG",
        "prior": {"source": "geostatistical", "seed": 4,
                  "variogram": {"model": "gaussian", "ranges": [500.0, 500.0, 5.0]},
                  "zones": [{"layers": [1, 1], "mean": 0.5, "std": 0.1},
                            {"layers": [1, 2], "mean": 0.5, "std": 0.1},
                            {"layers": [4, 5], "mean": 0.5, "std": 0.1},
                            {"region": "SATNUM", "number": 1, "mean": 0.5, "std": 0.1}]}})
    text = "\n".join(str(p) for p in prior_problems([bad], GRID))
    assert "the deck defines no NTG" in text
    assert "zone layers 4-5: layers must lie in 1..3, got [4, 5]" in text
    assert "the deck defines no SATNUM; it defines ['FIPNUM']" in text
    assert "every active cell must be in exactly one zone" in text
    assert "are in none and" in text and "in several" in text
    assert prior_problems([poro(), permx()], GRID) == []
