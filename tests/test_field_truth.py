"""A hidden field truth without the simulator: the truth's draw is a realisation of the case's
prior that is none of the members an ensemble of the case draws, reproducible for its seed
(a small block-centred grid built in numpy); and `hmflow reveal --campaign` judges an ensemble
run from hand-made stored artifacts laid out as the ensemble flow stores them
(:mod:`storage.ensemble`)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.grid import FieldGrid
from hmcore.fields.layout import Layout
from hmcore.fields.members import ensemble_table
from hmcore.fields.prior import draw_prior
from hmcore.fields.spec import FieldSpec
from hmcore.scenarios.field_truth import (
    FIELD_KIND,
    TRUTH_JSON,
    QuantityCheck,
    distinct_words,
    draw_truth,
    files_problems,
    reveal_field_truth,
    truth_field_seeds,
)
from storage import ArtifactStore
from storage.ensemble import ENSEMBLE_DOC, ENSEMBLE_FILE, FORECAST_STEP, ensemble_step

NX, NY, NZ, DX = 16, 12, 3, 100.0


def small_grid() -> FieldGrid:
    """16 x 12 x 3 cells of 100 m, 5 m thick, three inactive."""
    active = np.setdiff1d(np.arange(NX * NY * NZ), (0, 1, 17))
    i, j, k = active % NX, (active // NX) % NY, active // (NX * NY)
    centres = np.column_stack([(i + 0.5) * DX, (j + 0.5) * DX, 2000.0 + 5.0 * k + 2.5])
    return FieldGrid((NX, NY, NZ), active, centres, {}, {}, "small")


GRID = small_grid()
FIELDS = (
    FieldSpec.model_validate({
        "name": "poro", "keyword": "PORO", "low": 0.05, "high": 0.35,
        "prior": {"source": "geostatistical", "seed": 11,
                  "variogram": {"model": "spherical", "ranges": [800.0, 400.0, 10.0],
                                "azimuth": 30.0},
                  "zones": [{"layers": [k, k], "mean": m, "std": 0.03}
                            for k, m in ((1, 0.2), (2, 0.15), (3, 0.22))]}}),
    FieldSpec.model_validate({
        "name": "permx", "keyword": "PERMX", "copies": ["PERMY"], "low": 0.5, "high": 5000.0,
        "prior": {"source": "relation", "from": "poro", "intercept": -0.9, "slope": 12.6,
                  "scatter": 0.2, "seed": 12}}),
)


def test_the_truth_is_none_of_the_members_and_reproducible_for_its_seed():
    members = draw_prior(FIELDS, GRID, 40)  # the members of any ensemble of the case: 0..39
    truth = draw_truth(FIELDS, GRID, ("skin",), ensemble_seed=0, seed=3)
    again = draw_truth(FIELDS, GRID, ("skin",), ensemble_seed=0, seed=3)
    other = draw_truth(FIELDS, GRID, ("skin",), ensemble_seed=0, seed=4)
    other_case = draw_truth(FIELDS, GRID, ("skin",), ensemble_seed=1, seed=3)
    for name in ("poro", "permx"):
        t = truth.fields[name]
        assert t.shape == (GRID.n_active,) and np.isfinite(t).all()
        assert np.array_equal(t, again.fields[name])  # the seed reproduces it exactly
        assert not np.allclose(t, other.fields[name])  # another seed, another truth
        assert not np.allclose(t, other_case.fields[name])  # the case's seeds are its entropy
        # none of the members: every member differs from it in (nearly) every cell
        differs = np.mean(~np.isclose(members.values[name], t[None, :]), axis=1)
        assert differs.min() > 0.99, name
    assert np.array_equal(truth.scalars, again.scalars) and -1 <= truth.scalars[0] <= 1
    seeds = truth_field_seeds(FIELDS, 0, 3)
    assert set(seeds.values()).isdisjoint({0, 11, 12}) and len(set(seeds.values())) == 2
    assert dict(truth.field_seeds) == seeds and truth.entropy == (0, 11, 12)
    # a realisation of the prior: the porosity-permeability relation with its scatter
    resid = truth.fields["permx"] - (-0.9 + 12.6 * truth.fields["poro"])
    assert abs(float(resid.mean())) < 0.15 and 0.1 < float(resid.std()) < 0.3
    layer = GRID.ijk[:, 2]
    for k, mean in ((1, 0.2), (2, 0.15), (3, 0.22)):
        assert abs(float(truth.fields["poro"][layer == k].mean()) - mean) < 0.05
    X = truth.X
    assert X.shape == (1, 2 * GRID.n_active + 1) and X.dtype == np.float32


def test_a_truth_seed_skips_the_seeds_of_the_case():
    assert distinct_words([5, 7, 5, 9, 11], {7}, 3) == [5, 9, 11]
    with pytest.raises(ValueError, match="only 2 of 3"):
        distinct_words([5, 7, 5, 9], {7}, 3)


def test_a_files_prior_cannot_draw_a_truth():
    files = FieldSpec.model_validate({"name": "poro", "keyword": "PORO",
                                      "prior": {"source": "files", "folder": "/tmp/r"}})
    assert len(files_problems([files])) == 1 and "user's GRDECL files" in files_problems([files])[0]
    with pytest.raises(ValueError, match="no new realisation"):
        draw_truth([files], GRID, (), 0, 0)


# ----------------------------------------------------------------------------- reveal
N = 6
LAYOUT = Layout(("poro", "permx"), (), N)


def ensemble(poro: list[float], permx: list[float]) -> pd.DataFrame:
    """Members with one value each for every cell: ``(members, 2 N)``."""
    X = np.array([[p] * N + [k] * N for p, k in zip(poro, permx)], np.float32)
    return ensemble_table(X, LAYOUT)


def forecast_row(e, well, q, p90, p10, members=4):
    return {"ensemble": e, "well": well, "quantity": q, "label": "", "members": members,
            "P90": p90, "P50": (p90 + p10) / 2, "P10": p10, "min": p90, "max": p10,
            "end_days": 1000.0, "truth": None, "truth_inside": None}


@pytest.fixture
def stored(tmp_path):
    """An ensemble run ``e`` of 4 members and 2 assimilations as the flow stores it, and the
    hidden truth it is judged against (poro 0.2 and log10 permx 2.0 in every cell)."""
    store, meta = ArtifactStore(tmp_path / "store"), {"fields": ["poro", "permx"],
                                                     "scalars": [], "n_active": N}
    store.bind_settings("e", {"kind": "ensemble", "ensemble": EnsembleSpec(
        size=4, weights=(2.0, 1.0)).model_dump(mode="json")})
    members = {0: ([0.2, 0.3, 0.2, 0.3], [2.0, 3.0, 2.0, 3.0]),  # means 0.25, 2.5
               1: ([0.5] * 4, [4.0] * 4),  # an intermediate ensemble, not the posterior
               2: ([0.21, np.nan, 0.21, 0.21], [2.1, np.nan, 2.1, 2.1])}  # member 1 left out
    for i, (p, k) in members.items():
        store.put_files("e", ensemble_step(i), {"i": i}, {ENSEMBLE_FILE: ensemble(p, k),
                                                          ENSEMBLE_DOC: meta}, "test")
    table = pd.DataFrame([forecast_row("prior", "FIELD", "FOPT", 80.0, 120.0),
                          forecast_row("posterior", "FIELD", "FOPT", 101.0, 110.0, 3),
                          forecast_row("prior", "PRO1", "WOPT", 10.0, 90.0),
                          forecast_row("posterior", "PRO1", "WOPT", 45.0, 55.0, 3),
                          forecast_row("posterior", "FIELD", "FGPT", 5.0, 6.0, 3)])
    store.put_files("e", FORECAST_STEP, {}, {"forecast.parquet": table}, "test")
    hidden = tmp_path / "hidden"
    hidden.mkdir()
    ensemble([0.2], [2.0]).to_parquet(hidden / "truth.parquet")
    doc = {"kind": FIELD_KIND, "seed": 3, "truth_table": str(hidden / "truth.parquet"),
           "layout": meta, "fields": [{"name": "poro", "keyword": "PORO", "space": "value"},
                                      {"name": "permx", "keyword": "PERMX", "space": "log10"}],
           "forecast": [{"well": "FIELD", "quantity": "FOPT", "value": 100.0},
                        {"well": "FIELD", "quantity": "FWPT", "value": 7.0},
                        {"well": "FIELD", "quantity": "FGPT", "value": float("nan")},
                        {"well": "PRO1", "quantity": "WOPT", "value": 50.0}]}
    (hidden / TRUTH_JSON).write_text(json.dumps(doc))
    return tmp_path / "store", hidden / TRUTH_JSON


def test_reveal_judges_the_bands_and_the_mean_fields_from_the_store(stored):
    storage, hidden = stored
    r = reveal_field_truth(hidden, storage, "e")
    assert r.posterior_iteration == 2
    assert [(c.ensemble, c.well, c.quantity, c.inside) for c in r.checks] == [
        ("prior", "FIELD", "FOPT", True), ("posterior", "FIELD", "FOPT", False),
        ("prior", "PRO1", "WOPT", True), ("posterior", "PRO1", "WOPT", True)]  # no FWPT band,
    # and no truth of FGPT (NaN): judged only where the forecast and the truth both have it
    assert not r.fopt_inside and r.check("posterior", "FIELD", "FOPT").members == 3
    errors = {e.field: e for e in r.errors}
    assert errors["poro"].rmse_prior == pytest.approx(0.05, abs=1e-6)
    assert errors["poro"].rmse_posterior == pytest.approx(0.01, abs=1e-6)  # the left-out NaN skipped
    assert errors["permx"].rmse_prior == pytest.approx(0.5, abs=1e-6)
    assert errors["permx"].rmse_posterior == pytest.approx(0.1, abs=1e-6)
    assert errors["permx"].space == "log10"
    # the spread: members 0.2/0.3 (sd 0.0577), the truth 0.866 sd from their mean, as a member
    # is; the posterior's three members all alike: no spread, an error: collapsed
    assert errors["poro"].sd_prior == pytest.approx(np.sqrt(1 / 300), rel=1e-5)
    assert errors["poro"].error_to_spread[0] == pytest.approx(0.866, abs=1e-3)
    assert errors["permx"].error_to_spread[0] == pytest.approx(0.866, abs=1e-3)
    assert errors["poro"].sd_posterior == pytest.approx(0.0, abs=1e-6)
    assert errors["poro"].collapsed and errors["permx"].collapsed


def test_a_band_of_one_value_holds_a_truth_equal_to_it_within_the_simulators_convergence():
    """A well held at its rate control: every member and the truth give the same cumulative
    oil up to the simulator's convergence (6e-6 of the value measured on the small case)."""
    band = {"ensemble": "posterior", "well": "PROD1", "quantity": "WOPT", "P90": 210799.75,
            "P50": 210799.9, "P10": 210799.99, "members": 16}
    assert QuantityCheck(truth=210798.96, **band).inside  # 3.7e-6 below P90
    assert not QuantityCheck(truth=210790.0, **band).inside  # 4.6e-5 below
    assert QuantityCheck(truth=210798.96, **band).width == pytest.approx(1.14e-6, rel=0.01)


def invoke(args: list[str]):
    from hmflow.cli import app

    out = CliRunner().invoke(app, args, env={"COLUMNS": "300", "NO_COLOR": "1"})
    return out, " ".join(out.output.split())


def test_the_reveal_command_prints_the_verdict_and_refuses_bad_input(stored, restore_env,
                                                                    tmp_path):
    storage, hidden = stored
    out, text = invoke(["reveal", "--hidden", str(hidden), "--campaign", "e", "--storage",
                        str(storage)])
    assert out.exit_code == 1, text  # the truth's FOPT is outside the posterior's band
    assert ("posterior FIELD FOPT: truth 100, P90/P50/P10 101/105.5/110 (3 members, 8.5% wide) "
            "outside") in text
    assert "prior: 2 of 2 quantities inside P10-P90" in text
    assert "posterior: 1 of 2 quantities inside P10-P90" in text
    assert "field poro (value): RMSE of the mean to the truth, prior 0.05 -> posterior 0.01" in text
    assert "the members' spread 0.05774 -> 0; RMSE/spread 0.87 -> inf (collapsed: the update" \
        in text
    assert "FOPT OUTSIDE" in text and "Traceback" not in out.output
    missing, text = invoke(["reveal", "--hidden", str(hidden), "--campaign", "nope",
                            "--storage", str(storage)])
    assert missing.exit_code == 2 and "--campaign nope: no ensemble run of that name" in text
    both, text = invoke(["reveal", "--hidden", str(hidden), "--campaign", "e", "--diagnosis",
                         str(hidden)])
    assert both.exit_code == 2 and "one of them" in text
    effect = tmp_path / "hidden_effect.json"
    effect.write_text(json.dumps({"effect": None, "truth": {}}))
    wrong, text = invoke(["reveal", "--hidden", str(effect), "--campaign", "e", "--storage",
                          str(storage)])
    assert wrong.exit_code == 2 and "not a hidden field truth" in text


def test_hide_kind_field_refuses_bad_options_before_anything_runs(restore_env, tmp_path):
    out, text = invoke(["hide", "--kind", "field", "--out", str(tmp_path / "h"), "--deck",
                        str(tmp_path / "x.DATA"), "--value", "2"])
    assert out.exit_code == 2
    assert "--value: not for --kind field" in text and "--deck: not for --kind field" in text
    assert "--kind field needs --case" in text and not (tmp_path / "h").exists()
    other, text = invoke(["hide", "--kind", "well_skin", "--case", "c.toml", "--out",
                          str(tmp_path / "h")])
    assert other.exit_code == 2 and "--case c.toml: only with --kind field" in text
