"""The physics penalty: every check fires for some proposal inside the paper's box on PUNQ-S3,
is graded, is 0 at the deck's own values, and a real run that breaks one is stored penalised
(INVALID, with the check's kind) and is never selected as best."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from conftest import requires_opm
from hmcore.calibration.loop import best_record
from hmcore.model.case import PhysicsSettings
from hmcore.scoring.physics import Check, check_physics, check_responses

DECK_VALUES = {"poro_mult": 1.0, "permx_mult": 1.0, "permy_mult": 1.0, "permz_mult": 1.0,
               "skin": 5.0}
ONLY = {  # settings that leave one pre-simulation check alone to fire
    Check.KV_KH: {"trend_max_fraction": 1.0, "pore_volume_change_max": 10.0},
    Check.PORO_PERM_TREND: {"kv_kh_max_fraction": 1.0, "pore_volume_change_max": 10.0},
    Check.PORE_VOLUME: {"kv_kh_max_fraction": 1.0, "trend_max_fraction": 1.0},
}
BREAKS = {  # a proposal inside the paper's box that breaks each check
    Check.KV_KH: {"permx_mult": 0.3, "permy_mult": 0.3, "permz_mult": 3.0},
    Check.PORO_PERM_TREND: {"poro_mult": 0.8, "permx_mult": 3.0, "permy_mult": 3.0},
    Check.PORE_VOLUME: {"poro_mult": 1.2},
}


def _values(**changes) -> dict[str, float]:
    return {**DECK_VALUES, **changes}


def test_no_check_fires_at_the_decks_own_values(punq_case):
    check = check_physics(DECK_VALUES, punq_case.space, punq_case.info, punq_case.physics)
    assert check.valid and check.penalty == 0.0 and check.runnable


@pytest.mark.parametrize("kind", list(BREAKS), ids=lambda k: k.value)
def test_each_check_fires_inside_the_box_and_is_graded(punq_case, kind):
    settings = PhysicsSettings(**ONLY[kind])
    space, info = punq_case.space, punq_case.info
    assert not space.check_in_bounds(_values(**BREAKS[kind]))  # inside the paper's box
    hard = check_physics(_values(**BREAKS[kind]), space, info, settings)
    assert hard.kinds == (kind.value,), hard.violations
    assert hard.penalty > 0
    # half-way to the deck's values: a smaller excess, a smaller penalty (graded), or none
    half = {k: (v + DECK_VALUES[k]) / 2 for k, v in BREAKS[kind].items()}
    soft = check_physics(_values(**half), space, info, settings)
    assert soft.penalty < hard.penalty
    # the penalty is the weight times the excess: doubling the weight doubles it
    heavy = check_physics(_values(**BREAKS[kind]), space, info,
                          settings.model_copy(update={"violation_weight": 10.0}))
    assert heavy.penalty == pytest.approx(2 * hard.penalty)


def test_box_multipliers_act_on_their_box_only(punq_case):
    """A porosity multiplier on one layer changes the pore volume by that layer's share."""
    from hmcore.model.parameters import Parameter, ParameterSpace

    cells = punq_case.info.cells
    layer1 = cells.in_box((1, 19, 1, 28, 1, 1))
    assert 0 < layer1.sum() < cells.n
    share = cells.get("PORV")[layer1].sum() / cells.get("PORV").sum()
    space = ParameterSpace(parameters=(Parameter(name="poro_l1", kind="multiply",
                                                 keywords=("PORO",), box=(1, 19, 1, 28, 1, 1),
                                                 low=0.1, high=3.0),))
    limit = 0.5 * share  # a factor of 2 on layer 1 changes the total by exactly `share`
    check = check_physics({"poro_l1": 2.0}, space, punq_case.info,
                          PhysicsSettings(pore_volume_change_max=limit, trend_max_fraction=1.0))
    assert check.kinds == ("pore_volume",)
    assert check.found[0].excess == pytest.approx((share - limit) / limit)


def test_response_checks_fire_on_low_pressure_and_water_cut_outside_0_1(punq_info):
    settings = PhysicsSettings()
    ok = pd.DataFrame({"well": ["P"] * 4, "days": [0.0, 10.0, 10.0, 20.0],
                       "quantity": ["WBHP", "WBHP", "WWCT", "WWCT"],
                       "value": [0.0, 150.0, 0.2, 0.3]})  # BHP 0: the well is not open yet
    assert check_responses(ok, punq_info, settings).valid
    bad = ok.copy()
    bad.loc[1, "value"] = 0.5                  # below one atmosphere (METRIC deck: 1.01325 bar)
    bad.loc[3, "value"] = 1.2
    check = check_responses(bad, punq_info, settings)
    assert set(check.kinds) == {"pressure_min", "water_cut_range"}
    excess = {v.kind: v.excess for v in check.found}
    assert excess[Check.PRESSURE_MIN] == pytest.approx((1.01325 - 0.5) / 1.01325)
    assert excess[Check.WATER_CUT_RANGE] == pytest.approx(0.2)
    assert check.penalty == pytest.approx(settings.violation_weight * sum(excess.values()))


@requires_opm
@pytest.mark.opm
def test_a_real_run_that_breaks_the_physics_is_stored_penalised_and_never_best(punq_case,
                                                                                 tmp_path):
    """Real OPM runs on PUNQ-S3: the deck's values (valid), a proposal breaking the cell checks,
    and the deck's values under a minimum pressure above the producers' BHP floor (120 bar)."""
    from hmcore.scoring.evaluation import Status, evaluate

    strict = punq_case.__class__(**{**punq_case.__dict__, "physics": punq_case.physics.model_copy(
        update={"pressure_min": 150.0})})
    runs = {"valid": (punq_case, DECK_VALUES),
            "cells": (punq_case, _values(permx_mult=0.3, permy_mult=0.3, permz_mult=3.0,
                                         poro_mult=1.2)),
            "pressure": (strict, DECK_VALUES)}
    records = []
    for i, (name, (case, values)) in enumerate(runs.items()):
        ev = evaluate(case, values, tmp_path / name)
        rec = {"index": i, **ev.to_record()}
        records.append(rec)
        if name == "valid":
            assert ev.status is Status.COMPLETE and ev.penalty == 0.0
            continue
        assert ev.status is Status.INVALID, ev.reason
        assert ev.penalty > 0 and ev.reward == pytest.approx(-ev.E - ev.penalty)
        assert math.isfinite(ev.E)  # simulated and scored, then penalised
        if name == "cells":
            assert set(rec["violation_kinds"]) == {"kv_kh", "pore_volume", "poro_perm_trend"}
        else:
            assert rec["violation_kinds"] == ["pressure_min"]
    # the penalised runs are never best, even when their misfit is lower
    records[1]["E"] = records[2]["E"] = records[0]["E"] / 10
    assert best_record(records)["index"] == 0
