"""The ensemble report's builders on hand-made arrays (no simulator, no Prefect, no store): the
layer maps' statistics and where each cell lands, the truth read from a truth file and its
cumulatives, the forecast table with the truth inside or outside, and every figure drawn and
not blank, each one on the page."""

from __future__ import annotations

from dataclasses import replace

import io
import json

import matplotlib.image as mpimg
import numpy as np
import pandas as pd
import pytest
from matplotlib.figure import Figure

from hmcore.fields.forecast import ensemble_forecast
from hmcore.fields.grdecl import write_grdecl
from hmcore.fields.spec import FieldSpec
from hmcore.reporting import ensemble_figures as figs
from hmcore.reporting.ensemble import (
    EnsembleReportInputs,
    build,
    expected_figures,
    field_layer_maps,
    field_spreads,
    forecast_with_truth,
    mean_and_std,
    spread_markdown,
    to_layers,
)
from hmcore.reporting.ensemble_truth import FieldTruth, read_truth, truth_curves
from hmcore.reporting.figures import png

DIMS = (3, 2, 2)  # nx, ny, nz
ACTIVE = np.array([0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11])  # cell 5 (i=3, j=2, k=1) inactive
VARIOGRAM = {"model": "spherical", "ranges": [300.0, 300.0, 1.0]}
PORO = FieldSpec.model_validate({
    "name": "poro", "kind": "field", "keyword": "PORO", "low": 0.05, "high": 0.35,
    "prior": {"source": "geostatistical", "seed": 1, "variogram": VARIOGRAM,
              "zones": [{"layers": [1, 2], "mean": 0.2, "std": 0.03}]}})
PERMX = FieldSpec.model_validate({
    "name": "permx", "kind": "field", "keyword": "PERMX", "low": 0.5, "high": 5000.0,
    "prior": {"source": "relation", "from": "poro", "intercept": -0.9, "slope": 12.6,
              "scatter": 0.2, "seed": 2}})
DAYS = np.arange(30.0, 361.0, 30.0)


def test_a_cell_lands_on_its_layer_row_and_column_and_inactive_cells_are_blank():
    values = np.arange(ACTIVE.size, dtype=float)
    layers = to_layers(values, DIMS, ACTIVE)
    assert layers.shape == (2, 2, 3)  # (nz, ny, nx)
    assert layers[0, 0, 0] == 0 and layers[0, 1, 1] == 4  # global 4: i=2, j=2, k=1
    assert np.isnan(layers[0, 1, 2])  # global 5, inactive
    assert layers[1, 0, 0] == 5 and layers[1, 1, 2] == 10  # globals 6 and 11


def test_the_maps_leave_out_members_left_out_of_the_update():
    X = np.array([[1.0, 2.0], [3.0, 6.0], [np.nan, np.nan], [5.0, 10.0]])
    mean, std = mean_and_std(X)
    np.testing.assert_allclose(mean, [3.0, 6.0])
    np.testing.assert_allclose(std, [2.0, 4.0])  # ddof 1 over the three members kept


def inputs(truth: FieldTruth | None = None, members: int = 4) -> EnsembleReportInputs:
    rng = np.random.default_rng(7)
    n = ACTIVE.size
    prior = {"poro": rng.normal(0.2, 0.03, (members, n)),
             "permx": rng.normal(1.6, 0.4, (members, n))}
    posterior = {k: v.mean(axis=0) + 0.3 * (v - v.mean(axis=0)) for k, v in prior.items()}
    posterior["poro"][1] = np.nan  # a member left out
    curves, per_member = [], {"prior": {}, "posterior": {}}
    for e, scale in (("prior", 1.0), ("posterior", 0.3)):
        for m in range(members):
            rate = 100.0 * (1 + scale * rng.normal(0, 0.2))
            c = pd.DataFrame([
                *({"well": "P1", "quantity": q, "days": d, "value": v, "unit": u}
                  for d in DAYS for q, v, u in (
                      ("WOPR", rate, "SM3/DAY"), ("WWPR", 0.1 * d, "SM3/DAY"),
                      ("WGPR", 50.0 * rate, "SM3/DAY"), ("WBHP", 200 - 0.1 * d, "BARSA"),
                      ("WGOR", 50.0, "SM3/SM3"), ("WWCT", d / 720, ""),
                      ("WOPT", rate * d, "SM3"))),
                *({"well": "FIELD", "quantity": "FOPT", "days": d, "value": rate * d,
                   "unit": "SM3"} for d in DAYS)])
            per_member[e][m] = c
            curves.append(c.assign(ensemble=e, member=m))
    observed = pd.DataFrame([{"well": "P1", "quantity": q, "days": d, "observed": v,
                              "sigma": s, "period": "fit" if d <= 240 else "heldout",
                              "flowing": True}
                             for d in DAYS if d <= 300
                             for q, v, s in (("WBHP", 200 - 0.1 * d, 2.0),
                                             ("WGOR", 50.0, 5.0))])
    misfit = pd.DataFrame([{"iteration": i, "member": m, "status": "FAIL" if (i, m) == (0, 1)
                            else "COMPLETE", "failure": "", "misfit":
                            np.nan if (i, m) == (0, 1) else (5.0 / (i + 1)) * (1 + 0.1 * m)}
                           for i in range(3) for m in range(members)])
    summary = {"iterations": [{"iteration": i, "planned": members, "ran": members,
                               "failed": int(i == 0), "misfit_median": 5.0 / (i + 1),
                               "misfit_mean": 5.5 / (i + 1)} for i in range(3)],
               "runs": 3 * members, "failed": 1, "headline": "FOPT ..."}
    return EnsembleReportInputs(
        campaign="e", case_name="hand-made", case_source="case.toml", fields=(PORO, PERMX),
        dims=DIMS, active=ACTIVE, prior=prior, posterior=posterior, observed=observed,
        history_end=240.0, curves=pd.concat(curves, ignore_index=True), misfit=misfit,
        forecast=ensemble_forecast(per_member, ["P1"]), summary=summary, wells=("P1",),
        weights=(2.0, 1.0), truth=truth, code="test")


def truth_of(fopt_rate: float) -> FieldTruth:
    responses = pd.DataFrame([{"well": "P1", "days": d, "quantity": "WOPR", "value": fopt_rate}
                              for d in DAYS])
    return FieldTruth({"poro": np.full(ACTIVE.size, 0.21)}, truth_curves(responses), "hand")


def test_the_truths_cumulatives_are_integrated_from_its_rates():
    responses = pd.DataFrame([{"well": w, "days": d, "quantity": "WOPR", "value": r}
                              for w, r in (("P1", 10.0), ("P2", 5.0)) for d in (10.0, 20.0, 40.0)])
    curves = truth_curves(responses)
    wopt = curves[(curves.well == "P1") & (curves.quantity == "WOPT")].sort_values("days")
    np.testing.assert_allclose(wopt.value, [100.0, 200.0, 400.0])
    fopt = curves[(curves.well == "FIELD") & (curves.quantity == "FOPT")].sort_values("days")
    np.testing.assert_allclose(fopt.value, [150.0, 300.0, 600.0])


def test_the_forecast_table_says_whether_the_truth_is_inside_p90_p10():
    data = inputs()
    fopt = data.forecast[(data.forecast.well == "FIELD") & (data.forecast.quantity == "FOPT")]
    prior = fopt[fopt.ensemble == "prior"].iloc[0]
    inside = forecast_with_truth(data.forecast, truth_of(prior.P50 / DAYS[-1]).curves)
    outside = forecast_with_truth(data.forecast, truth_of(2 * fopt.P10.max() / DAYS[-1]).curves)
    row = inside[(inside.well == "FIELD") & (inside.ensemble == "prior")].iloc[0]
    assert row.truth == pytest.approx(prior.P50) and row.truth_inside
    assert prior.P90 < prior.P50 < prior.P10  # so the test can fail
    assert outside[outside.well == "FIELD"].truth_inside.tolist() == [False, False]
    assert forecast_with_truth(data.forecast, None).truth.isna().all()


def png_pixels(data: bytes) -> np.ndarray:
    return mpimg.imread(io.BytesIO(data), format="png")


def drawn(data: bytes) -> bool:
    """A PNG with data drawn on it: more than 0.2 % of its pixels in a strong colour (axes,
    text, grid lines and the shaded periods are grey or pale; every series is coloured)."""
    rgb = png_pixels(data)[..., :3]
    return float(((rgb.max(axis=-1) - rgb.min(axis=-1)) > 0.25).mean()) > 0.002


def test_empty_axes_are_not_drawn():
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    ax.set_title("nothing here")
    ax.axvspan(0.6, 0.9, color="#f3e9d2")  # the held-back shading alone is no data
    ax.grid(alpha=0.3)
    assert not drawn(png(fig))
    ax.plot([0, 1], [0, 1], color="#1f5fbf", lw=2)
    assert drawn(png(fig))


def test_every_figure_is_drawn_and_on_the_page_with_the_truth_table():
    data = inputs(truth_of(100.0))
    report = build(data)
    names = expected_figures(data)
    assert list(report.figures) == names
    assert names[:3] == ["misfit_boxes.png", "forecast_fans.png", "well__P1.png"]
    assert {f"map__{f}__k{k:02d}.png" for f in ("poro", "permx") for k in (1, 2)} <= set(names)
    assert all(drawn(report.figures[n]) for n in names)
    for n in names:
        assert f'data-figure="{n}"' in report.html and f"]({n})" in report.markdown
    assert "| quantity | ensemble | members | P90 | P50 | P10 | truth | truth in [P90, P10] |" \
        in report.markdown
    assert report.doc["truth_fields"] == ["poro"] and len(report.doc["forecast"]) == 4
    assert "after update 1" in report.markdown and "hmflow report --campaign e" in report.markdown


def test_without_a_truth_the_table_has_no_truth_column_and_the_maps_four_panels():
    data = inputs()
    report = build(data)
    assert "truth in [P90, P10]" not in report.markdown
    assert "Truth: unknown" in report.markdown
    # the fields' spread, in the report and its JSON (None where the truth would be)
    assert spread_markdown(field_spreads(data)) in report.markdown
    assert report.doc["fields"][1]["field"] == "permx"
    assert report.doc["fields"][1]["rmse_prior"] is None
    layers = field_layer_maps(data, "poro")
    assert len(layers) == 2 and set(layers[0]) == set(figs.MAP_TITLES) - {"truth"}
    with_truth = field_layer_maps(inputs(truth_of(100.0)), "poro")
    np.testing.assert_allclose(with_truth[1]["truth"][np.isfinite(with_truth[1]["truth"])],
                               0.21)


def test_the_fields_spread_is_tabled_and_a_posterior_surer_than_right_is_called_collapsed():
    """The posterior keeps 30 % of the prior's spread (its members' deviations are 0.3 times
    the prior's); without a truth that is all the table says. A truth 0.1 from the members'
    mean in every cell (about 11 posterior spreads) makes the posterior collapsed; a truth at
    the posterior's mean does not."""
    data = inputs()
    table = spread_markdown(field_spreads(data))
    assert "| field | space | spread prior | spread posterior | kept |\n" in table
    permx = next(f for f in field_spreads(data) if f.field == "permx")
    assert permx.kept == pytest.approx(0.3) and "| permx | log10 |" in table
    assert np.isnan(permx.rmse_prior) and not permx.collapsed
    kept = np.delete(data.posterior["poro"], 1, axis=0)
    for truth, collapsed in ((kept.mean(axis=0) + 0.1, True), (kept.mean(axis=0), False)):
        known = replace(data, truth=FieldTruth({"poro": truth}, None, "hand"))
        poro = field_spreads(known)[0]
        assert poro.collapsed is collapsed
        assert poro.rmse_posterior == pytest.approx(0.1 if collapsed else 0.0, abs=1e-9)
        assert poro.sd_posterior == pytest.approx(np.sqrt(np.mean(kept.var(axis=0, ddof=1))))
        assert ("| **yes**" if collapsed else "| no") in spread_markdown(field_spreads(known))
        # 0.1 from the mean is 3.3 prior spreads: the prior misses this truth already
        assert poro.prior_holds_truth is not collapsed


def test_the_posterior_map_is_the_mean_of_the_members_kept():
    data = inputs()
    layers = field_layer_maps(data, "poro")
    kept = np.delete(data.posterior["poro"], 1, axis=0)
    expected = to_layers(kept.mean(axis=0), DIMS, ACTIVE)
    np.testing.assert_allclose(layers[0]["posterior mean"], expected[0], equal_nan=True)
    assert np.nanmax(layers[0]["posterior std"]) < np.nanmax(layers[0]["prior std"])


def test_the_truth_file_gives_fields_in_update_space_on_active_cells(tmp_path):
    poro = np.linspace(0.1, 0.3, 12)
    perm = np.full(12, 100.0)
    write_grdecl(tmp_path / "truth_fields.GRDECL", {"PORO": poro, "PERMX": perm})
    pd.DataFrame([{"well": "P1", "days": d, "quantity": "WOPR", "value": 1.0} for d in DAYS]
                 ).to_csv(tmp_path / "truth_responses.csv", index=False)
    (tmp_path / "truth.json").write_text(json.dumps({
        "fields": {"poro": "truth_fields.GRDECL", "permx": "truth_fields.GRDECL"},
        "files": {"truth_responses": "truth_responses.csv"}}))
    truth = read_truth(tmp_path / "case.toml", (PORO, PERMX), DIMS, ACTIVE)
    np.testing.assert_allclose(truth.fields["poro"], poro[ACTIVE], rtol=1e-6)
    np.testing.assert_allclose(truth.fields["permx"], 2.0)  # log10 of 100 mD
    fopt = truth.curves[(truth.curves.well == "FIELD") & (truth.curves.quantity == "FOPT")]
    assert fopt.value.max() == pytest.approx(DAYS[-1])
    assert read_truth(tmp_path / "elsewhere" / "case.toml", (PORO,), DIMS, ACTIVE) is None


def test_the_misfit_boxes_draw_a_round_whose_members_all_failed():
    misfit = pd.DataFrame({"iteration": [0, 0, 1], "member": [0, 1, 0],
                           "status": ["COMPLETE", "COMPLETE", "FAIL"], "failure": ["", "", "crash"],
                           "misfit": [3.0, 4.0, np.nan]})
    assert drawn(figs.misfit_boxes(misfit, {0: "prior", 1: "posterior"}))


def test_a_hidden_truth_file_gives_every_field_from_its_one_grdecl(tmp_path):
    hidden = tmp_path / "hidden"
    hidden.mkdir()
    write_grdecl(hidden / "truth.GRDECL", {"PORO": np.full(12, 0.25), "PERMX": np.full(12, 10.0),
                                           "PERMY": np.full(12, 10.0)})
    pd.DataFrame([{"well": "P1", "days": d, "quantity": "WOPR", "value": 2.0} for d in DAYS]
                 ).to_csv(hidden / "truth_responses.csv", index=False)
    (hidden / "hidden_truth.json").write_text(json.dumps({  # as hmflow hide --kind field
        "kind": "field", "fields": [{"name": "poro", "keyword": "PORO", "space": "value"}],
        "truth_grdecl": "/moved/away/truth.GRDECL", "summary": "/moved/away/TRUTH.SMSPEC"}))
    truth = read_truth(hidden / "case.toml", (PORO, PERMX), DIMS, ACTIVE, ("P1",))
    np.testing.assert_allclose(truth.fields["poro"], 0.25)
    np.testing.assert_allclose(truth.fields["permx"], 1.0)
    wopt = truth.curves[(truth.curves.well == "P1") & (truth.curves.quantity == "WOPT")]
    assert wopt.value.max() == pytest.approx(2.0 * DAYS[-1])
    assert truth.source == str(hidden / "hidden_truth.json")
