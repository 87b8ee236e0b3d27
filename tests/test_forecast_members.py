"""A campaign's forecast members and band (``hmcore.simulation.forecast``): the members are
the best calls by the objective that chose the best call, the best first; a truth equal to a
band collapsed to a point (a well at its rate control) is inside it."""

from __future__ import annotations

import pandas as pd
import pytest

from hmcore.simulation.forecast import choose_members, forecast_table, inside_band


def _record(index: int, E: float, likelihood: float, status: str = "COMPLETE") -> dict:
    return {"index": index, "status": status, "E": E, "likelihood": likelihood,
            "params": {"a": float(index)}, "phase": "explore"}


def test_members_are_the_best_calls_by_the_objective_that_chose_best_first():
    records = [_record(0, E=1.0, likelihood=0.5), _record(1, E=0.1, likelihood=3.0),
               _record(2, E=0.5, likelihood=0.2), _record(3, E=0.05, likelihood=9.0,
                                                          status="INVALID")]
    assert choose_members(records, 2, "likelihood").indices == (2, 0)
    assert choose_members(records, 2, "E").indices == (1, 2)
    assert choose_members(records, 5).indices == (1, 2, 0)  # penalised never a member
    with pytest.raises(ValueError, match="k=0"):
        choose_members(records, 0)


def test_a_truth_equal_to_a_point_band_up_to_convergence_is_inside():
    assert inside_band(491800.0, 491800.0, 491800.0 * (1 + 3e-6))
    assert not inside_band(491800.0, 491800.0, 491800.0 * (1 + 3e-4))
    assert inside_band(1.0, 2.0, 1.5) and not inside_band(1.0, 2.0, 2.1)


def test_the_forecast_table_calls_a_rate_controlled_well_s_truth_inside():
    def run(oil: float) -> pd.DataFrame:
        return pd.DataFrame({"well": ["P1", "P1"], "quantity": ["WOPT", "WOPT"],
                             "days": [0.0, 100.0], "value": [0.0, oil], "unit": "SM3"})

    curves = {1: run(491800.0), 2: run(491800.0), 3: run(491800.0)}
    table = forecast_table(curves, ["P1"], truth=run(491800.0 * (1 + 2e-6)))
    row = table[(table.well == "P1") & (table.quantity == "WOPT")].iloc[0]
    assert row.P90 == row.P10 == 491800.0 and bool(row.truth_inside)


def test_curves_drawn_for_another_best_call_are_stale(tmp_path):
    from storage import ArtifactStore
    from tasks.curves import stale

    store = ArtifactStore(tmp_path)
    assert not stale(str(tmp_path), "c")  # nothing stored: nothing to redo

    def results(objective: str):
        return store.put_files("c", "results", {"objective": objective},
                               {"records.json": {"records": [], "objective": objective}}, "t")

    def curves(made_from, objective: str | None):
        doc = {"kind": "near_best"} | ({"objective": objective} if objective else {})
        return store.put_files("c", "curves", {"results": made_from.ref(), "doc": doc},
                               {"forecast.json": doc}, "t")

    first = results("likelihood")
    curves(first, None)  # chosen by E (an earlier hmflow) for a likelihood campaign
    assert stale(str(tmp_path), "c")
    curves(first, "likelihood")
    assert not stale(str(tmp_path), "c")
    results("E")  # consolidated again since: drawn from other results
    assert stale(str(tmp_path), "c")
