"""Property tests (hypothesis) and a hand-computed example for alignment, misfit and metrics.

Nothing here runs a simulator: observed and simulated tables are generated.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hmcore.scoring.alignment import align
from hmcore.scoring.metrics import CATEGORIES, OPTIONAL, cmatch, compute_metrics, nmse, r2
from hmcore.scoring.misfit import PRIMARY, misfit, response_range

QUANTITIES = ("WBHP", "WOPR", "WWPR", "WGPR", "WGOR", "WWCT")
PRIMARY_QUANTITIES = tuple(PRIMARY.values())
WELLS = ("PRO-1", "PRO-4", "PRO-11")

SETTINGS = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

values_st = st.floats(min_value=0.0, max_value=1e4, allow_nan=False, allow_infinity=False)


@st.composite
def tables(draw, perfect: bool = False, min_series: int = 1, max_series: int = 4):
    """(observed, simulated) long tables on the same integer days, one series per (well, q).

    At least one series is a primary quantity so that E is defined. With ``perfect`` the
    simulated values equal the observed ones.
    """
    first = (draw(st.sampled_from(WELLS)), draw(st.sampled_from(PRIMARY_QUANTITIES)))
    others = draw(st.lists(st.tuples(st.sampled_from(WELLS), st.sampled_from(QUANTITIES)),
                           max_size=max_series - 1))
    keys = list(dict.fromkeys([first, *others]))
    obs_rows, sim_rows = [], []
    for well, q in keys:
        days = draw(st.lists(st.integers(0, 3000), min_size=1, max_size=10, unique=True))
        for d in days:
            o = draw(values_st)
            s = o if perfect else draw(values_st)
            obs_rows.append({"well": well, "quantity": q, "days": float(d), "value": o})
            sim_rows.append({"well": well, "quantity": q, "days": float(d), "value": s})
    return pd.DataFrame(obs_rows), pd.DataFrame(sim_rows)


def _shuffled(df: pd.DataFrame, seed: int) -> pd.DataFrame:
    return df.sample(frac=1.0, random_state=seed).reset_index(drop=True)


def _close(a: float, b: float, rel: float = 1e-9, abs_: float = 1e-12) -> bool:
    if a is None or b is None:
        return a is b
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return a == pytest.approx(b, rel=rel, abs=abs_)


def _assert_nested_close(a, b, path: str = "") -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), f"keys differ at {path}"
        for k in a:
            _assert_nested_close(a[k], b[k], f"{path}.{k}")
    else:
        assert _close(float(a), float(b), rel=1e-7, abs_=1e-9), f"{path}: {a} != {b}"


# ----------------------------------------------------------------------------- perfect match
@SETTINGS
@given(tables(perfect=True))
def test_perfect_match_scores_zero_misfit_and_full_marks(data):
    obs, sim = data
    al = align(obs, sim, tolerance_days=0.5)
    assert al.n_matched == len(obs) and al.coverage == 1.0
    for variant in ("mean", "robust"):
        m = misfit(al.pairs, variant=variant)
        assert m.E == 0.0
        assert all(v == 0.0 for v in m.per_response.values())
    met = compute_metrics(al.pairs)
    for cat, score in met["categories"].items():
        if score["n"] == 0:
            continue
        assert score["nmse"] == 0.0
        assert score["cmatch"] == 100.0
        # R^2 is 1, or undefined (NaN) for a record without variance
        assert score["r2"] == 1.0 or math.isnan(score["r2"])
    assert met["macro"]["nmse"] == 0.0 and met["macro"]["cmatch"] == 100.0


# ----------------------------------------------------------------------------- sign / ranges
@SETTINGS
@given(tables(), st.floats(0.0, 10.0))
def test_misfit_and_metrics_are_never_negative(data, lam):
    obs, sim = data
    pairs = align(obs, sim, tolerance_days=0.5).pairs
    for variant in ("mean", "robust"):
        m = misfit(pairs, variant=variant, robust_lambda=lam)
        assert m.E >= 0.0
        assert all(v >= 0.0 for v in m.per_response.values())
        assert all(v >= 0.0 for d in m.per_well_response.values() for v in d.values())
    met = compute_metrics(pairs)
    for score in [*met["categories"].values(),
                  *(s for cats in met["wells"].values() for s in cats.values())]:
        if score["n"] == 0:
            assert math.isnan(score["nmse"]) and math.isnan(score["cmatch"])
            continue
        assert score["nmse"] >= 0.0
        assert 0.0 < score["cmatch"] <= 100.0
        assert score["cmatch"] == pytest.approx(100.0 / (1.0 + score["nmse"]))
        assert math.isnan(score["r2"]) or score["r2"] <= 1.0 + 1e-12


@SETTINGS
@given(st.lists(values_st, min_size=1, max_size=30))
def test_response_range_is_positive(values):
    assert response_range(np.asarray(values)) > 0.0


# ----------------------------------------------------------------------------- row order
@SETTINGS
@given(tables(), st.integers(0, 2**31 - 1), st.integers(0, 2**31 - 1))
def test_results_do_not_depend_on_row_order(data, seed_obs, seed_sim):
    obs, sim = data
    a = align(obs, sim, tolerance_days=0.5)
    b = align(_shuffled(obs, seed_obs), _shuffled(sim, seed_sim), tolerance_days=0.5)
    assert a.n_matched == b.n_matched and a.coverage == b.coverage
    key = ["well", "quantity", "days"]
    pa = a.pairs.sort_values(key).reset_index(drop=True)
    pb = b.pairs.sort_values(key).reset_index(drop=True)
    pd.testing.assert_frame_equal(pa, pb)
    for variant in ("mean", "robust"):
        ma, mb = misfit(a.pairs, variant), misfit(b.pairs, variant)
        assert _close(ma.E, mb.E)
        _assert_nested_close(ma.per_response, mb.per_response)
        _assert_nested_close(ma.per_well_response, mb.per_well_response)
    _assert_nested_close(compute_metrics(a.pairs), compute_metrics(b.pairs))


# ----------------------------------------------------------------------------- tolerance
@SETTINGS
@given(tables(), st.lists(st.tuples(st.sampled_from((*WELLS, "GHOST")), st.sampled_from(QUANTITIES),
                                    st.integers(1, 2000), values_st), min_size=1, max_size=10),
       st.floats(0.5, 20.0))
def test_points_outside_the_tolerance_are_ignored_and_lower_coverage(data, extra, tol):
    obs, sim = data
    base = align(obs, sim, tolerance_days=tol)
    # extra observations far after the last simulated day (> tol away from every sim time)
    last = sim["days"].max()
    far = pd.DataFrame([{"well": w, "quantity": q, "days": last + tol + 1.0 + d, "value": v}
                        for w, q, d, v in extra])
    more = align(pd.concat([obs, far], ignore_index=True), sim, tolerance_days=tol)
    assert more.n_matched == base.n_matched
    assert more.n_observed == base.n_observed + len(far)
    assert more.coverage == pytest.approx(base.n_matched / (len(obs) + len(far)))
    assert more.coverage < base.coverage or base.coverage == 0.0
    m0, m1 = misfit(base.pairs), misfit(more.pairs)
    assert _close(m0.E, m1.E)
    _assert_nested_close(compute_metrics(base.pairs), compute_metrics(more.pairs))


@SETTINGS
@given(tables(), st.floats(0.1, 40.0))
def test_alignment_matches_a_brute_force_nearest_search(data, tol):
    """The vectorised search pairs each observation with the nearest simulated time of its
    well and quantity (the earlier one on a tie; of equal times the later row)."""
    obs, sim = data
    got = align(obs, sim, tolerance_days=tol).pairs
    expected = []
    for _, o in obs.iterrows():
        cand = sim[(sim.well == o.well) & (sim.quantity == o.quantity)]
        if cand.empty:
            continue
        d = (cand.days - o.days).abs()
        best = cand[d == d.min()]
        best = best[best.days == best.days.min()].iloc[-1]
        if abs(best.days - o.days) <= tol + 1e-9:
            expected.append((o.well, o.quantity, float(o.days), float(best.days),
                             float(o.value), float(best.value)))
    key = lambda r: r[:3] + r[4:5]  # noqa: E731
    actual = [(r.well, r.quantity, r.days, r.sim_days, r.observed, r.simulated)
              for r in got.itertuples()]
    assert sorted(actual, key=key) == sorted(expected, key=key)


def test_a_point_just_inside_the_tolerance_is_matched_and_just_outside_is_not():
    sim = pd.DataFrame({"well": "W", "quantity": "WBHP", "days": [100.0], "value": [200.0]})
    obs = pd.DataFrame({"well": "W", "quantity": "WBHP", "days": [70.0, 69.9, 130.0, 130.1],
                        "value": [1.0, 2.0, 3.0, 4.0]})
    al = align(obs, sim, tolerance_days=30.0)
    assert sorted(al.pairs["days"]) == [70.0, 130.0]
    assert al.coverage == pytest.approx(0.5)


# ----------------------------------------------------------------------------- robust variant
@SETTINGS
@given(tables(), st.floats(0.0, 10.0))
def test_robust_variant_is_never_below_the_mean_variant(data, lam):
    obs, sim = data
    pairs = align(obs, sim, tolerance_days=0.5).pairs
    mean = misfit(pairs, "mean")
    robust = misfit(pairs, "robust", robust_lambda=lam)
    assert robust.E >= mean.E
    worst = max(v for d in robust.per_well_response.values() for v in d.values())
    assert robust.E == pytest.approx(mean.E + lam * worst, rel=1e-12, abs=1e-15)
    assert misfit(pairs, "robust", robust_lambda=0.0).E == pytest.approx(mean.E)


def test_unknown_variant_is_rejected():
    pairs = pd.DataFrame({"well": ["W"], "quantity": ["WBHP"], "observed": [1.0],
                          "simulated": [2.0]})
    with pytest.raises(ValueError, match="variant"):
        misfit(pairs, "median")


# ----------------------------------------------------------------------------- nearest time
@SETTINGS
@given(st.lists(st.floats(0, 5000, allow_nan=False), min_size=1, max_size=20, unique=True),
       st.lists(st.floats(-100, 5100, allow_nan=False), min_size=1, max_size=20),
       st.integers(0, 2**31 - 1))
def test_nearest_simulated_time_is_picked(sim_days, obs_days, seed):
    sim_days = sorted(set(round(d, 2) for d in sim_days))
    values = {d: 1000.0 + i for i, d in enumerate(sim_days)}  # value identifies the sim time
    sim = _shuffled(pd.DataFrame({"well": "W", "quantity": "WBHP", "days": sim_days,
                                  "value": [values[d] for d in sim_days]}), seed)
    obs = pd.DataFrame({"well": "W", "quantity": "WBHP", "days": obs_days,
                        "value": np.zeros(len(obs_days))})
    al = align(obs, sim, tolerance_days=1e9)
    assert al.n_matched == len(obs_days)
    t = np.asarray(sim_days)
    for row in al.pairs.itertuples(index=False):
        best = np.min(np.abs(t - row.days))
        assert abs(row.sim_days - row.days) == pytest.approx(best, abs=1e-9)
        assert row.simulated == values[row.sim_days]


@SETTINGS
@given(st.lists(st.integers(0, 500), min_size=1, max_size=15, unique=True),
       st.lists(st.integers(-50, 550), min_size=1, max_size=15), st.integers(1, 40))
def test_matched_exactly_when_the_nearest_time_is_within_tolerance(sim_days, obs_days, tol):
    sim = pd.DataFrame({"well": "W", "quantity": "WOPR", "days": [float(d) for d in sim_days],
                        "value": 1.0})
    obs = pd.DataFrame({"well": "W", "quantity": "WOPR", "days": [float(d) for d in obs_days],
                        "value": 1.0})
    al = align(obs, sim, tolerance_days=float(tol))
    expected = sum(min(abs(o - s) for s in sim_days) <= tol for o in obs_days)
    assert al.n_matched == expected
    assert al.coverage == pytest.approx(expected / len(obs_days))


def test_nearest_time_on_a_hand_made_record():
    sim = pd.DataFrame({"well": "W", "quantity": "WBHP", "days": [0.0, 10.0, 31.0, 59.0],
                        "value": [1.0, 2.0, 3.0, 4.0]})
    obs = pd.DataFrame({"well": "W", "quantity": "WBHP", "days": [-3.0, 4.0, 6.0, 30.0, 45.5, 80.0],
                        "value": 0.0})
    pairs = align(obs, sim, tolerance_days=30.0).pairs
    # -3 -> 0; 4 -> 0 (4 < 6); 6 -> 10; 30 -> 31; 45.5 -> 59 (13.5 < 14.5); 80 -> 59 (21 <= 30)
    assert list(pairs["sim_days"]) == [0.0, 0.0, 10.0, 31.0, 59.0, 59.0]
    assert list(pairs["simulated"]) == [1.0, 1.0, 2.0, 3.0, 4.0, 4.0]


def test_records_are_matched_only_within_the_same_well_and_quantity():
    sim = pd.DataFrame({"well": ["A", "B", "A"], "quantity": ["WBHP", "WBHP", "WOPR"],
                        "days": [10.0, 10.0, 10.0], "value": [100.0, 200.0, 300.0]})
    obs = pd.DataFrame({"well": ["B", "A", "C"], "quantity": ["WBHP", "WOPR", "WBHP"],
                        "days": [10.0, 10.0, 10.0], "value": [0.0, 0.0, 0.0]})
    pairs = align(obs, sim, 5.0).pairs.set_index(["well", "quantity"])
    assert pairs.loc[("B", "WBHP"), "simulated"] == 200.0
    assert pairs.loc[("A", "WOPR"), "simulated"] == 300.0
    assert ("C", "WBHP") not in pairs.index


# ----------------------------------------------------------------------------- hand example
def test_hand_computed_example():
    # Well A, BHP on days 10/20/30: observed 200, 210, 220; simulated 202, 208, 220.
    # Well A, oil rate on days 10/20: observed 100, 100 (flat); simulated 110, 100.
    # Well B, GOR (diagnostic only, not in E) on day 10: observed 50, simulated 60.
    obs = pd.DataFrame({
        "well": ["A", "A", "A", "A", "A", "B"],
        "quantity": ["WBHP", "WBHP", "WBHP", "WOPR", "WOPR", "WGOR"],
        "days": [10.0, 20.0, 30.0, 10.0, 20.0, 10.0],
        "value": [200.0, 210.0, 220.0, 100.0, 100.0, 50.0],
    })
    sim = pd.DataFrame({
        "well": ["A", "A", "A", "A", "A", "B"],
        "quantity": ["WBHP", "WBHP", "WBHP", "WOPR", "WOPR", "WGOR"],
        # simulated times 1 day off: still the nearest within a 5-day tolerance
        "days": [11.0, 21.0, 29.0, 9.0, 20.0, 10.0],
        "value": [202.0, 208.0, 220.0, 110.0, 100.0, 60.0],
    })
    al = align(obs, sim, tolerance_days=5.0)
    assert al.coverage == 1.0
    m = misfit(al.pairs)
    # bhp: range = 220 - 200 = 20; z = (2/20, -2/20, 0) -> z^2 = 0.01, 0.01, 0 -> MSE = 0.02/3
    # oil: flat record -> range = max(|100|, 1) = 100; z = (10/100, 0) -> MSE = 0.01/2 = 0.005
    # water, gas: no data. E = mean(0.02/3, 0.005) = 0.0058333...
    assert m.per_response == pytest.approx({"bhp": 0.02 / 3, "oil": 0.005})
    assert m.E == pytest.approx((0.02 / 3 + 0.005) / 2)
    # robust (lambda 0.5): worst (well, category) = A/bhp = 0.02/3 -> E + 0.5 * 0.0066667
    rob = misfit(al.pairs, "robust", robust_lambda=0.5)
    assert rob.worst == pytest.approx(0.02 / 3)
    assert rob.E == pytest.approx((0.02 / 3 + 0.005) / 2 + 0.5 * 0.02 / 3)
    # fixed ranges (as score_responses passes them): bhp range 40 -> z^2 = 1/400, 1/400, 0
    fixed = misfit(al.pairs, ranges={"bhp": 40.0, "oil": 100.0})
    assert fixed.per_response["bhp"] == pytest.approx(2 / 400 / 3)

    met = compute_metrics(al.pairs)
    bhp = met["categories"]["bhp"]
    # NMSE = (2^2 + 2^2 + 0) / (200^2 + 210^2 + 220^2) = 8 / 132500
    assert bhp["n"] == 3
    assert bhp["nmse"] == pytest.approx(8 / 132500)
    # R^2 = 1 - 8 / ((200-210)^2 + 0 + (220-210)^2) = 1 - 8/200 = 0.96
    assert bhp["r2"] == pytest.approx(0.96)
    assert bhp["cmatch"] == pytest.approx(100 / (1 + 8 / 132500))
    oil = met["categories"]["oil"]
    # NMSE = 10^2 / (100^2 + 100^2) = 0.005; R^2 undefined for a flat record
    assert oil["nmse"] == pytest.approx(0.005) and math.isnan(oil["r2"])
    gor = met["categories"]["gor"]
    # NMSE = 10^2 / 50^2 = 0.04 -> C_match = 100 / 1.04
    assert gor["nmse"] == pytest.approx(0.04) and gor["cmatch"] == pytest.approx(100 / 1.04)
    assert met["categories"]["water"]["n"] == 0 and math.isnan(met["categories"]["water"]["nmse"])
    # macro over the primary categories with data (oil, bhp); the diagnostic gor is left out
    assert met["macro"]["nmse"] == pytest.approx((8 / 132500 + 0.005) / 2)
    assert met["macro"]["r2"] == pytest.approx(0.96)
    # the paper's macro C_match: 100 / (1 + macro NMSE), not the mean of the categories' C_match
    assert met["macro"]["cmatch"] == pytest.approx(100 / (1 + (8 / 132500 + 0.005) / 2))
    assert met["macro"]["cmatch"] != pytest.approx((100 / (1 + 8 / 132500) + 100 / 1.005) / 2)
    assert set(met["wells"]) == {"A", "B"} and set(met["wells"]["B"]) == {"gor"}


def test_metric_functions_on_small_vectors():
    y, yhat = np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 5.0])
    # NMSE = 4 / (1 + 4 + 9) = 2/7; R^2 = 1 - 4 / 2 = -1; C_match = 100 / (1 + 2/7) = 77.78
    assert nmse(y, yhat) == pytest.approx(2 / 7)
    assert r2(y, yhat) == pytest.approx(-1.0)
    assert cmatch(2 / 7) == pytest.approx(700 / 9)
    assert math.isnan(r2(np.array([3.0, 3.0]), np.array([3.0, 4.0])))


@SETTINGS
@given(tables())
def test_category_counts_add_up(data):
    obs, sim = data
    pairs = align(obs, sim, 0.5).pairs
    met = compute_metrics(pairs)
    # every category, except injection rates when the history has none
    present = {c for c, q in CATEGORIES.items() if c not in OPTIONAL or (pairs.quantity == q).any()}
    assert set(met["categories"]) == present
    for cat, q in CATEGORIES.items():
        if cat not in present:
            continue
        n = int((pairs["quantity"] == q).sum())
        left_out = met["categories"][cat].get("n_excluded", 0)
        assert met["categories"][cat]["n"] + left_out == n
        assert sum(w.get(cat, {"n": 0})["n"] for w in met["wells"].values()) + left_out == n
        assert left_out == sum(c for why in met["excluded"].get(cat, {}).values()
                               for c in why.values())


def test_no_primary_data_gives_nan_misfit():
    obs = pd.DataFrame({"well": ["A"], "quantity": ["WGOR"], "days": [1.0], "value": [50.0]})
    m = misfit(align(obs, obs, 1.0).pairs)
    assert math.isnan(m.E)


def test_shut_in_records_are_left_out_of_gor_and_water_cut_and_counted():
    """GOR = Qg/Qo and WCT = Qw/(Qw+Qo) are undefined while a well is shut in: a hand-built
    history with one shut-in report (all rates 0) leaves it out of both ratios, counts it per
    well and reason, and keeps it in the primary categories (a 0 = 0 rate match)."""
    days = [10.0, 20.0, 30.0]
    obs = pd.DataFrame({
        "well": ["P"] * 12, "days": days * 4,
        "quantity": ["WOPR"] * 3 + ["WWPR"] * 3 + ["WGOR"] * 3 + ["WWCT"] * 3,
        "value": [100.0, 0.0, 80.0, 10.0, 0.0, 20.0, 50.0, 0.0, 60.0, 0.1, 0.0, 0.2],
        "flowing": [True, False, True] * 4})
    sim = obs.drop(columns="flowing").copy()
    sim.loc[sim.quantity == "WGOR", "value"] = [55.0, 0.0, 60.0]
    sim.loc[sim.quantity == "WWCT", "value"] = [0.1, 0.0, 0.3]
    met = compute_metrics(align(obs, sim, 1.0).pairs)
    gor, wct = met["categories"]["gor"], met["categories"]["wct"]
    assert (gor["n"], gor["n_excluded"]) == (2, 1) and (wct["n"], wct["n_excluded"]) == (2, 1)
    assert met["excluded"] == {"gor": {"P": {"shut_in_observed": 1}},
                               "wct": {"P": {"shut_in_observed": 1}}}
    # only the two flowing records: NMSE = 5^2 / (50^2 + 60^2); WCT (0.1)^2 / (0.1^2 + 0.2^2)
    assert gor["nmse"] == pytest.approx(25 / (2500 + 3600))
    assert wct["nmse"] == pytest.approx(0.01 / 0.05)
    # R^2 over the defined records: the 0 = 0 shut-in match no longer inflates it
    assert gor["r2"] == pytest.approx(1 - 25 / 50)
    assert met["categories"]["oil"]["n"] == 3 and "n_excluded" not in met["categories"]["oil"]
    # a simulated well that makes no oil where the observed one flows: no simulated GOR
    sim2 = sim.copy()
    sim2.loc[(sim2.quantity == "WOPR") & (sim2.days == 30.0), "value"] = 0.0
    met2 = compute_metrics(align(obs, sim2, 1.0).pairs)
    assert met2["excluded"]["gor"]["P"] == {"shut_in_observed": 1, "no_rate_simulated": 1}
    assert met2["excluded"]["wct"]["P"] == {"shut_in_observed": 1}  # Qw + Qo = 20 > 0
    # without observed rates, the flowing flag marks the shut-in record
    ratios_only = obs[obs.quantity.isin(["WGOR", "WWCT"])]
    met3 = compute_metrics(align(ratios_only, sim, 1.0).pairs)
    assert met3["categories"]["gor"]["n_excluded"] == 1


def test_ratio_exclusions_take_the_first_rate_of_a_day_and_the_flag_without_one():
    """Hand-built pairs: a day whose oil rate is reported twice (0 first, then 5) takes the
    first (shut in); a water cut whose water rate was not observed falls back to the
    ``flowing`` flag; wells are listed in sorted order in ``wells`` and ``excluded``."""
    rows = [  # well, quantity, days, observed, simulated, flowing
        ("PRO-2", "WOPR", 10.0, 0.0, 1.0, True), ("PRO-2", "WOPR", 10.0, 5.0, 5.0, True),
        ("PRO-2", "WGOR", 10.0, 90.0, 80.0, True), ("PRO-2", "WOPR", 20.0, 4.0, 0.0, True),
        ("PRO-2", "WGOR", 20.0, 90.0, 80.0, True),
        ("PRO-10", "WOPR", 10.0, 5.0, 5.0, False), ("PRO-10", "WWPR", 10.0, np.nan, 1.0, False),
        ("PRO-10", "WWCT", 10.0, 0.2, 0.1, False), ("PRO-10", "WOPR", 20.0, 5.0, 5.0, True),
        ("PRO-10", "WWPR", 20.0, 1.0, 1.0, True), ("PRO-10", "WWCT", 20.0, 0.2, 0.1, True)]
    pairs = pd.DataFrame(rows, columns=["well", "quantity", "days", "observed", "simulated",
                                        "flowing"])
    pairs["sim_days"], pairs["sigma"], pairs["derived"] = pairs["days"], np.nan, False
    met = compute_metrics(pairs)
    assert met["excluded"] == {
        "gor": {"PRO-2": {"no_rate_simulated": 1, "shut_in_observed": 1}},
        "wct": {"PRO-10": {"shut_in_observed": 1}}}
    assert list(met["wells"]) == ["PRO-10", "PRO-2"]  # sorted as text, as pandas groups them
    assert met["categories"]["gor"]["n"] == 0 and met["categories"]["wct"]["n"] == 1
    assert met["wells"]["PRO-10"]["wct"] == {**met["wells"]["PRO-10"]["wct"], "n": 1,
                                             "n_excluded": 1}
