"""`hmflow hide --kind field` with the real simulator: on the field version of the small
synthetic case (tests/test_ensemble_flow.py's ``field_case``: a PORO field per layer and a
PERMX = PERMY field from it, the simulator a logging wrapper of OPM Flow), one truth run over
the whole schedule through the members' INCLUDE, and the files of the hidden case."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from test_ensemble_flow import field_case
from typer.testing import CliRunner

from hmcore.fields.grdecl import read_grdecl
from hmcore.fields.grid import read_grid
from hmcore.fields.members import INCLUDE_NAME
from hmcore.model.case import load_case_file
from hmcore.scenarios.field_truth import TRUTH_JSON
from hmcore.scoring.observations import ObservationSet
from hmcore.simulation.curves import FIELD, read_curves, value_at_end

pytestmark = [pytest.mark.opm]


def invoke(args: list[str]):
    from hmflow.cli import app

    out = CliRunner().invoke(app, args, env={"COLUMNS": "400", "NO_COLOR": "1"})
    return out, " ".join(out.output.split())


def test_hide_kind_field_runs_one_truth_and_writes_the_hidden_case(tmp_path, small_case,
                                                                   restore_env):
    case, log = field_case(tmp_path / "case", small_case, "never-fails",
                           "size = 4\nweights = [1.0]\n")
    out = tmp_path / "hidden"
    made, text = invoke(["hide", "--kind", "field", "--case", str(case), "--out", str(out),
                         "--seed", "3"])
    assert made.exit_code == 0, made.output
    assert f"hmflow reveal --hidden {out / TRUTH_JSON} --campaign NAME" in text
    assert log.read_text().split() == ["truth-run"]  # one simulator call: the truth's run
    doc = json.loads((out / TRUTH_JSON).read_text())
    assert doc["kind"] == "field" and doc["seed"] == 3
    assert set(doc["field_seeds"].values()).isdisjoint({0, 11, 12})
    original = load_case_file(case)
    # the truth run read the truth's fields through the members' INCLUDE, at the end of GRID
    run = out / "truth-run"
    deck = next(run.glob("*.DATA")).read_text()
    assert f"'{run / INCLUDE_NAME}'" in deck
    included, truth = read_grdecl(run / INCLUDE_NAME), read_grdecl(out / "truth.GRDECL")
    assert set(truth) == {"PORO", "PERMX", "PERMY"} and doc["truth_grdecl"] == str(out / "truth.GRDECL")
    for k in truth:
        assert np.array_equal(included[k], truth[k])
    grid = read_grid(original.deck)
    poro = truth["PORO"][grid.active]
    assert 0.05 <= poro.min() and poro.max() <= 0.35 and poro.std() > 0.01
    # FOPT of the truth run's own summary, over the whole schedule
    summary = next(run.glob("*.SMSPEC"))
    curves = read_curves(summary, sorted(original.info.wells))
    assert float(curves.days.max()) == pytest.approx(original.info.end_days, abs=0.5)
    assert doc["FOPT"] == pytest.approx(value_at_end(curves, FIELD, "FOPT"), rel=1e-12)
    assert doc["FOPT"] > 0 and doc["schedule_end_days"] == original.info.end_days
    wopt = {r["well"]: r["value"] for r in doc["forecast"] if r["quantity"] == "WOPT"}
    assert sorted(wopt) == sorted(original.info.wells)
    assert sum(wopt.values()) == pytest.approx(doc["FOPT"], rel=1e-3)
    # the observed history: the case's wells to its history end, PUNQ-S3's noise, no sigma
    observed = pd.read_csv(out / "observed.csv")
    assert "sigma" not in observed.columns
    assert set(observed.well) == set(original.observed.well)
    end = original.history_end_days
    assert observed.days.max() <= end and doc["history_end_days"] == end
    hidden = load_case_file(out / "case.toml")
    assert hidden.name == "hidden" and hidden.fields == original.fields
    assert hidden.ensemble == original.ensemble and hidden.deck == original.deck.resolve()
    assert hidden.history_end_days == end and hidden.heldout_observed.empty
    assert len(ObservationSet.from_case(hidden).vector_index("fit")) > 0
    responses = pd.read_csv(out / "truth_responses.csv")
    observed["day"], responses["day"] = observed.days.round(2), responses.days.round(2)
    bhp = observed[(observed.quantity == "WBHP") & (observed.flowing == 1)].merge(
        responses[responses.quantity == "WBHP"], on=["well", "day"], suffixes=("", "_truth"))
    noise = (bhp.value - bhp.value_truth).to_numpy()
    assert len(noise) > 50 and 1.5 < noise.std() < 4.5  # 3 bar flowing (AR(1) in time)
    # an existing folder is never overwritten, and a case without fields is refused
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    again, text = invoke(["hide", "--kind", "field", "--case", str(case), "--out", str(out)])
    assert again.exit_code == 2 and "exists and is not an empty directory" in text
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before
    plain, text = invoke(["hide", "--kind", "field", "--case", str(small_case), "--out",
                          str(tmp_path / "plain")])
    assert plain.exit_code == 2 and "has no field parameter" in text
    assert not (tmp_path / "plain").exists() and log.read_text().split() == ["truth-run"]


def test_the_field_version_of_the_small_case_is_written_with_its_fields_and_raised_targets(
        tmp_path):
    """hmcore.scenarios.synthetic_fields: the small case's deck with the producers' oil targets
    raised, the two fields and the [ensemble] keys in its case file (one OPM run, the
    synthetic truth's)."""
    from hmcore.scenarios.synthetic_deck import SMALL_LAYOUT
    from hmcore.scenarios.synthetic_fields import RATE_SCALE, write_field_case

    case = load_case_file(write_field_case(tmp_path / "fields", 0,
                                           {"size": 40, "localisation": "adaptive"}))
    assert case.name == "synthetic-small-fields"
    assert [f.name for f in case.fields] == ["poro", "permx"] and case.space.names == []
    assert case.ensemble.size == 40 and case.ensemble.localisation == "adaptive"
    deck = case.deck.read_text()
    for w in SMALL_LAYOUT.wells:
        assert f" '{w.name}' 'OPEN' 'ORAT' {w.orat_sm3_day * RATE_SCALE:.1f} " in deck
    assert not case.observed.empty
