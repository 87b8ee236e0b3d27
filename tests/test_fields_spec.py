"""Field specifications: what a case file may say about a field parameter and the ensemble, and
the rule (with the values) it is told when it says something wrong. No deck needed."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.fieldset import draw_order, field_set_problems
from hmcore.fields.spec import FieldSpec, FilesPrior, GeostatisticalPrior, Variogram

VARIOGRAM = {"model": "spherical", "ranges": [2000.0, 800.0, 10.0], "azimuth": 140.0}


def geostat(**over) -> dict:
    spec = {"name": "poro", "keyword": "PORO",
            "prior": {"source": "geostatistical", "seed": 1, "variogram": VARIOGRAM,
                      "zones": [{"layers": [1, 2], "mean": 0.2, "std": 0.03}]}}
    spec.update(over)
    return spec


def relation(name="permx", source="poro", seed=2, **over) -> dict:
    spec = {"name": name, "keyword": "PERMX",
            "prior": {"source": "relation", "from": source, "intercept": 0.77, "slope": 9.02,
                      "scatter": 0.3, "seed": seed}}
    spec.update(over)
    return spec


def refused(model, data) -> str:
    """The errors as the case loader shows them: the rule, then the value given (which the
    loader appends to pydantic's own messages; a validator's message states it itself)."""
    with pytest.raises(ValidationError) as info:
        model.model_validate(data)
    return " | ".join(e["msg"] + ("" if e["type"] == "value_error" else f", got {e['input']!r}")
                      for e in info.value.errors())


def test_a_geostatistical_field_with_defaults():
    f = FieldSpec.model_validate(geostat())
    assert f.kind == "field" and f.keyword == "PORO" and not f.in_log
    assert f.bounds == (1e-3, 1.0) and f.written == ("PORO",)
    assert isinstance(f.prior, GeostatisticalPrior)
    assert f.prior.variogram_of(f.prior.zones[0]).ranges == (2000.0, 800.0, 10.0)


def test_permeability_is_in_log_space_by_default_and_copies_are_written():
    f = FieldSpec.model_validate(relation(copies=["permy"], low=0.1, high=5000))
    assert f.in_log and f.copies == ("PERMY",) and f.written == ("PERMX", "PERMY")
    assert f.source_field == "poro" and f.bounds == (0.1, 5000.0)
    assert not FieldSpec.model_validate(relation(log=False)).in_log


def test_a_folder_of_realisations():
    f = FieldSpec.model_validate({"name": "k", "keyword": "PERMX",
                                  "prior": {"source": "files", "folder": "priors/permx"}})
    assert isinstance(f.prior, FilesPrior) and f.prior.pattern == "*.grdecl"


@pytest.mark.parametrize("change, words", [
    ({"keyword": "SWAT"}, ["one of", "PORO", "'SWAT'"]),
    ({"low": 0.5, "high": 0.1}, ["low < high", "low=0.5", "high=0.1"]),
    ({"keyword": "PERMX", "low": 0.0}, ["log space needs low > 0", "low=0.0"]),
    ({"low": 0.0}, ["PORO bounds must satisfy 0 < low and high <= 1", "low=0.0, high=1.0"]),
    ({"high": 1.5}, ["high <= 1", "high=1.5"]),
    ({"copies": ["PORO"]}, ["must not repeat", "PORO"]),
    ({"copies": ["SGAS"]}, ["copies must be keywords", "SGAS"]),
    ({"kind": "multiply"}, ["'field'"]),
])
def test_bad_fields_are_refused_with_the_rule_and_the_values(change, words):
    message = refused(FieldSpec, geostat(**change))
    assert all(w in message for w in words), message


@pytest.mark.parametrize("zone, words", [
    ({"layers": [3, 1], "mean": 0.2, "std": 0.1}, ["k1 <= k2", "[3, 1]"]),
    ({"mean": 0.2, "std": 0.1}, ["either layers", "region"]),
    ({"layers": [1, 1], "region": "FIPNUM", "number": 1, "mean": 0.2, "std": 0.1},
     ["not both"]),
    ({"region": "FIPNUM", "mean": 0.2, "std": 0.1}, ["needs number"]),
    ({"layers": [1, 1], "mean": 0.2, "std": -0.1}, ["greater than or equal to 0"]),
    ({"layers": [1, 1], "mean": True, "std": 0.1}, ["valid number"]),
])
def test_bad_zones_are_refused(zone, words):
    data = geostat()
    data["prior"]["zones"] = [zone]
    message = refused(FieldSpec, data)
    assert all(w in message for w in words), message


@pytest.mark.parametrize("variogram, words", [
    ({"ranges": [500.0, 800.0, 5.0]}, ["major >= minor", "major=500.0", "minor=800.0"]),
    ({"ranges": [500.0, 100.0, 0.0]}, ["must all be > 0", "[500.0, 100.0, 0.0]"]),
    ({"ranges": [500.0, 100.0, 5.0], "azimuth": [170.0, 110.0]}, ["lo <= hi"]),
    ({"ranges": [500.0, 100.0, 5.0], "model": "cubic"}, ["gaussian", "'cubic'"]),
    ({"ranges": [500.0, 100.0, 5.0], "model": "matern", "nu": 0.0}, ["nu must be > 0"]),
])
def test_bad_variograms_are_refused(variogram, words):
    message = refused(Variogram, variogram)
    assert all(w in message for w in words), message


def test_a_zone_without_any_variogram_is_refused():
    data = geostat()
    del data["prior"]["variogram"]
    assert "no variogram" in refused(FieldSpec, data)


def test_a_cosimulation_correlation_outside_minus_one_one_is_refused():
    data = {"name": "permx", "keyword": "PERMX",
            "prior": {"source": "cosimulation", "from": "poro", "correlation": 1.2, "seed": 3,
                      "zones": [{"layers": [1, 2], "mean": 2.0, "std": 0.5}]}}
    assert "correlation must lie in [-1, 1], got 1.2" in refused(FieldSpec, data)


def test_the_default_ensemble_is_ert_s():
    e = EnsembleSpec()
    assert e.size == 100 and e.weights == (4.0, 2.0, 1.0)
    assert e.alphas == pytest.approx((7.0, 3.5, 1.75))
    assert sum(1 / a for a in e.alphas) == pytest.approx(1.0)
    assert e.minimum == 50 and e.localisation == "auto"


def test_auto_localisation_takes_its_radius_from_the_priors_variograms():
    """sqrt(major x minor) of the largest range ellipse over the zones; a relation adds none;
    a files prior alone gives no radius, so no localisation, and says why; a stated
    localisation is kept as stated."""
    zone_own = geostat(name="ntg", keyword="NTG", prior={
        "source": "geostatistical", "seed": 3, "variogram": VARIOGRAM, "zones": [
            {"layers": [1, 1], "mean": 0.8, "std": 0.1, "variogram": {
                "ranges": [3000.0, 800.0, 2.0]}},
            {"layers": [2, 2], "mean": 0.8, "std": 0.1}]})
    fields = [FieldSpec.model_validate(f) for f in (geostat(), relation(), zone_own)]
    auto = EnsembleSpec().resolved(fields)
    expected = max(np.sqrt(VARIOGRAM["ranges"][0] * VARIOGRAM["ranges"][1]), np.sqrt(3000 * 800))
    assert auto.localisation == "distance" and auto.radius == pytest.approx(expected)
    assert "auto: distance" in auto.chosen and EnsembleSpec().chosen == ""
    files = FieldSpec.model_validate({"name": "k", "keyword": "PERMX",
                                      "prior": {"source": "files", "folder": "x"}})
    none = EnsembleSpec().resolved([files])
    assert none.localisation == "none" and none.radius is None and "no field's prior" in none.chosen
    stated = EnsembleSpec(localisation="adaptive")
    assert stated.resolved(fields) is stated
    assert auto.model_dump()["localisation"] == "distance"  # stored settings: the concrete one


@pytest.mark.parametrize("data, words", [
    ({"size": 1}, ["greater than or equal to 2"]),
    ({"weights": [4.0, 0.0]}, ["weights must all be > 0", "[4.0, 0.0]"]),
    ({"size": 10, "min_realizations": 11}, ["min_realizations must lie in [2, size = 10]",
                                            "got 11"]),
    ({"localisation": "distance"}, ["needs radius > 0", "radius = None"]),
    ({"localisation": "distance", "radius": -5.0}, ["radius = -5.0"]),
    ({"radius": 500.0}, ["only for localisation = 'distance'", "not 'auto'",
                         "'auto', the default, takes the radius from the prior's variograms"]),
    ({"localisation": "kriging"}, ["'none'", "'adaptive'", "'distance'"]),
    ({"sise": 10}, ["Extra inputs are not permitted"]),
])
def test_bad_ensembles_are_refused(data, words):
    message = refused(EnsembleSpec, data)
    assert all(w in message for w in words), message


def test_fields_together_report_every_problem_at_once():
    fields = [FieldSpec.model_validate(geostat()),
              FieldSpec.model_validate(relation(source="porosity", seed=1)),
              FieldSpec.model_validate(relation(name="permx2", seed=5, copies=["PERMY"])),
              FieldSpec.model_validate({"name": "permz", "keyword": "PERMZ",
                                        "prior": {"source": "cosimulation", "from": "permx2",
                                                  "correlation": 0.5, "seed": 6, "zones": [
                                                      {"layers": [1, 1], "mean": 1.0,
                                                       "std": 0.5}]}})]
    problems = field_set_problems(fields)
    text = "\n".join(str(p) for p in problems)
    assert "prior.from = 'porosity' names no field" in text
    assert "keyword PERMX is written by fields 'permx' and 'permx2'" in text
    assert "prior.seed = 1 is also field 'poro''s" in text
    assert "a co-simulation needs a source with a normal score" in text
    assert len(problems) == 4


def test_sources_are_drawn_first_and_cycles_are_named():
    a = FieldSpec.model_validate(relation(name="a", source="b", seed=1))
    b = FieldSpec.model_validate(geostat(name="b"))
    c = FieldSpec.model_validate(relation(name="c", source="a", seed=3, keyword="PERMZ"))
    assert [f.name for f in draw_order([c, a, b])] == ["b", "a", "c"]
    x = FieldSpec.model_validate(relation(name="x", source="y", seed=1))
    y = FieldSpec.model_validate(relation(name="y", source="x", seed=2, keyword="PERMZ"))
    problems = field_set_problems([x, y])
    assert len(problems) == 1 and "cycle: x -> y -> x" in problems[0].what
