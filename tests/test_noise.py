"""The noise a fit assumes: estimated from histories without sigma (within a factor 1.5 on a
series with known noise and signal steps at shut-ins, no simulator), floors that never hide the
signal (a water cut of 3e-5 is flagged uninformative, not weighted by a floor of 0.01), and the
case file's ``[noise]`` section (ERT's ABS / REL / RELMIN and a correlation length) changing the
weights as stated, with bad values refused by file and key, all at once."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from conftest import requires_opm, requires_punq, write_case_toml

from hmcore.cases import load_case
from hmcore.errors import CaseError
from hmcore.model.noise_section import NoiseLevel, QuantityNoise
from hmcore.scoring.noise import SIGMA_FLOOR, NoiseSeries, fit_noise
from hmcore.scoring.noise_scale import censored_sigma
from hmcore.scoring.noise_table import format_noise_table, noise_summary, noise_table
from hmcore.scoring.observations import ObservationSet

FACTOR = 1.5


def ar1(rng: np.random.Generator, n: int, rho: float, law: str = "normal") -> np.ndarray:
    """Unit-variance AR(1) series; ``law`` 't3' draws Student-t innovations (heavy tails)."""
    e = rng.standard_t(3, n) / math.sqrt(3.0) if law == "t3" else rng.standard_normal(n)
    z = np.empty(n)
    z[0] = e[0]
    for t in range(1, n):
        z[t] = rho * z[t - 1] + math.sqrt(1 - rho * rho) * e[t]
    return z


def history(rng: np.random.Generator, *, wells: int = 4, years: int = 6, bhp_sigma: float = 3.0,
            shut_sigma: float = 1.0, gor_rel: float = 0.08, wct: float = 3e-5,
            wct_rel: float = 0.03, rho: float = 0.5, law: str = "normal") -> pd.DataFrame:
    """Monthly rows of BHP, GOR, water cut and oil rate with known noise (column ``true``).

    Every well is shut in one month a year (its BHP builds up ~25 bar, GOR and water cut are
    not measured) and its rate steps from 100 to 150 after the first year (BHP drops ~10 bar),
    after every reopening the BHP carries a decaying transient, the pressure declines; the GOR
    rises slowly, the water cut is ~3e-5 and grows: signal steps the noise must not absorb.
    """
    days = 30.4 * np.arange(1, 12 * years + 1)
    shut = (np.arange(days.size) % 12) == 11
    rows = []
    for w in range(wells):
        well = f"P{w + 1}"
        rate = np.where(shut, 0.0, np.where(days < 365, 100.0, 150.0))
        last_open = np.maximum.accumulate(np.where(np.r_[True, shut[:-1]], days, 0.0))
        bhp = 250.0 - 0.01 * days - 0.1 * rate + 8.0 * np.exp(-(days - last_open) / 40.0)
        bhp = np.where(shut, 262.0 - 0.008 * days, bhp) + 3.0 * w
        sig = np.where(shut, shut_sigma, bhp_sigma)
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WOPR", "value": rate,
                                  "true": np.nan, "flowing": ~shut}))
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WBHP",
                                  "value": bhp + sig * ar1(rng, days.size, rho, law),
                                  "true": sig, "flowing": ~shut}))
        f = days[~shut]
        gor = 80.0 * (1 + 0.0001 * f)
        rows.append(pd.DataFrame({"well": well, "days": f, "quantity": "WGOR",
                                  "value": gor * (1 + gor_rel * ar1(rng, f.size, rho, law)),
                                  "true": gor_rel * gor, "flowing": True}))
        cut = wct * (1 + f / 1000.0)
        rows.append(pd.DataFrame({"well": well, "days": f, "quantity": "WWCT",
                                  "value": cut * (1 + wct_rel * ar1(rng, f.size, rho, law)),
                                  "true": wct_rel * cut, "flowing": True}))
    return pd.concat(rows, ignore_index=True)


def ratios(obs: ObservationSet, data: pd.DataFrame, quantity: str, segment: str) -> pd.Series:
    """Estimated / true sigma of the fitted rows of one quantity and segment."""
    rows = obs.rows.assign(segment=list(obs.segment)).merge(
        data[["well", "quantity", "days", "true"]], on=["well", "quantity", "days"])
    rows = rows[(rows.quantity == quantity) & (rows.segment == segment)
                & (rows.period == "fit") & rows.in_vector]
    return rows.sigma / rows.true


# ============================================================================ the estimate
@pytest.mark.parametrize("rho,law", [(0.0, "normal"), (0.5, "normal"), (0.0, "t3")])
def test_noise_is_estimated_within_a_factor_of_1_5_despite_steps_at_shut_ins(rho, law):
    rng = np.random.default_rng(7)
    data = history(rng, rho=rho, law=law)
    obs = ObservationSet.from_observed(data.drop(columns="true"), 1600.0)
    bhp = ratios(obs, data, "WBHP", "flowing")
    gor = ratios(obs, data, "WGOR", "before")
    assert set(obs.rows[obs.rows.quantity == "WBHP"].sigma_source) >= {"estimated"}
    assert 1 / FACTOR < bhp.median() < FACTOR, bhp.median()
    assert 1 / FACTOR < gor.median() < FACTOR, gor.median()
    assert abs(obs.rho["WBHP"] - rho) < 0.3


def test_rate_steps_and_shut_ins_start_new_runs_of_signal():
    """A 40-bar step at a rate change and at every reopening: without the runs it would be
    noise; the estimate stays near the 2 bar of the data."""
    rng = np.random.default_rng(3)
    days = 30.0 * np.arange(1, 49)
    step = np.where((days // 240) % 2 == 0, 0.0, 40.0)
    rate = np.where(step > 0, 200.0, 100.0)
    rows = []
    for well in ("A", "B", "C"):
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WOPR",
                                  "value": rate, "flowing": True}))
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WBHP",
                                  "value": 200 - step - 0.01 * days + 2 * rng.standard_normal(
                                      days.size), "flowing": True}))
    obs = ObservationSet.from_observed(pd.concat(rows, ignore_index=True), 1440.0)
    sigma = obs.rows[obs.rows.quantity == "WBHP"].sigma.median()
    assert 2 / FACTOR < sigma < 2 * FACTOR


def test_a_water_cut_of_3e_5_is_flagged_uninformative_and_not_hidden_by_the_floor():
    rng = np.random.default_rng(11)
    data = history(rng)
    obs = ObservationSet.from_observed(data.drop(columns="true"), 1600.0)
    wct = obs.rows[(obs.rows.quantity == "WWCT") & obs.rows.in_vector]
    assert {("WWCT", w) for w in wct.well.unique()} <= obs.uninformative
    assert not any(q == "WBHP" for q, _ in obs.uninformative)
    assert wct.sigma.max() < 1e-4 < SIGMA_FLOOR["WWCT"]  # weighed by its own noise
    assert wct.sigma.min() > 0
    r = ratios(obs, data, "WWCT", "before")
    assert 0.2 < r.median() < 5  # a level of the right order (the series is flagged)
    table = noise_table(obs)
    assert table[table.quantity == "WWCT"].uninformative.all()
    assert not table[table.quantity == "WBHP"].uninformative.any()
    assert "UNINFORMATIVE" in format_noise_table(obs)
    assert set(obs.noise_report["WWCT"]["uninformative"]) == set(wct.well)


def test_an_all_zero_water_cut_is_uninformative_at_the_floor():
    rows = pd.DataFrame({"well": "A", "days": 30.0 * np.arange(1, 25), "quantity": "WWCT",
                         "value": 0.0, "flowing": True})
    obs = ObservationSet.from_observed(rows, 500.0)
    assert ("WWCT", "A") in obs.uninformative
    assert np.allclose(obs.rows.sigma, SIGMA_FLOOR["WWCT"])


def test_a_dry_water_cut_clipped_at_zero_gets_the_noise_level():
    rng = np.random.default_rng(5)
    values = np.clip(0.02 * ar1(rng, 400, 0.6), 0.0, 1.0)
    assert 0.02 / FACTOR < censored_sigma(values) < 0.02 * FACTOR


def test_the_correlation_and_level_of_long_series_are_recovered_jointly():
    rng = np.random.default_rng(2)
    series = [NoiseSeries(20 * np.linspace(0, 1, 120) + 2.0 * ar1(rng, 120, 0.7))
              for _ in range(6)]
    fit = fit_noise(series)
    assert abs(fit.rho - 0.7) < 0.15 and fit.rho_identified
    assert all(2.0 / FACTOR < s < 2.0 * FACTOR for s in fit.sigma)
    assert 2.0 / 1.25 < np.median(fit.sigma) < 2.0 * 1.25


# ============================================================================ [noise] section
def test_the_noise_section_changes_the_weights_as_stated():
    rng = np.random.default_rng(1)
    data = history(rng, wells=3).drop(columns="true")
    given = (data.quantity == "WBHP") & (data.well == "P3")
    data["sigma"] = np.where(given, 0.7, np.nan)  # the data's own sigma comes first
    stated = {
        "WBHP": QuantityNoise(absolute=2.0, correlation_days=0.0,
                              wells={"P2": NoiseLevel(absolute=1.0, correlation_days=60.8)}),
        "WGOR": QuantityNoise(relative=0.05, relative_min=4.5),
    }
    obs = ObservationSet.from_observed(data, 1600.0, noise=stated)
    rows = obs.rows
    bhp = rows[rows.quantity == "WBHP"]
    assert np.allclose(bhp[bhp.well == "P1"].sigma, 2.0)
    assert np.allclose(bhp[bhp.well == "P2"].sigma, 1.0)
    assert np.allclose(bhp[bhp.well == "P3"].sigma, 0.7)
    assert set(bhp[bhp.well != "P3"].sigma_source) == {"stated"}
    assert set(bhp[bhp.well == "P3"].sigma_source) == {"given"}
    gor = rows[rows.quantity == "WGOR"]
    assert np.allclose(gor.sigma, np.maximum(0.05 * gor.observed.abs(), 4.5))
    assert set(gor.sigma_source) == {"stated"}
    assert set(rows[rows.quantity == "WWCT"].sigma_source) <= {"estimated", "pooled", "floor"}
    # the correlation: white for the quantity, exp(-spacing / 60.8 days) for P2
    assert obs.rho["WBHP"] == 0.0
    assert obs.rho_well["WBHP"]["P2"] == pytest.approx(math.exp(-30.4 / 60.8))
    # the weights: a residual of 1 bar is 0.5 sigma at P1, 1 at P2
    sim = data[["well", "days", "quantity"]].assign(value=data.value + 1.0)
    z = obs.standardized(sim)
    assert np.allclose(z[(rows.quantity == "WBHP") & (rows.well == "P1")], 0.5)
    assert np.allclose(z[(rows.quantity == "WBHP") & (rows.well == "P2")], 1.0)
    # the statement survives re-estimation from residuals
    again = obs.refine(sim, data)
    assert np.allclose(again.rows[again.rows.quantity == "WGOR"].sigma, gor.sigma)
    summary = noise_summary(obs)
    bhp_rows = summary[(summary.quantity == "WBHP") & (summary.segment == "flowing")]
    assert set(bhp_rows.source) == {"stated", "given"} and len(bhp_rows) == 3


def test_a_statement_of_correlation_only_leaves_the_level_to_the_estimate():
    rng = np.random.default_rng(4)
    data = history(rng, wells=3).drop(columns="true")
    obs = ObservationSet.from_observed(
        data, 1600.0, noise={"WBHP": QuantityNoise(correlation_days=30.4)})
    assert obs.rho["WBHP"] == pytest.approx(math.exp(-1.0))
    assert set(obs.rows[obs.rows.quantity == "WBHP"].sigma_source) <= {"estimated", "pooled",
                                                                        "default"}


def test_noise_levels_follow_ert_modes():
    v = np.array([0.0, 10.0, 200.0])
    assert NoiseLevel(absolute=3.0).mode == "ABS"
    assert np.allclose(NoiseLevel(absolute=3.0).sigma(v), 3.0)
    assert NoiseLevel(relative=0.1).mode == "REL"
    assert np.allclose(NoiseLevel(relative=0.1).sigma(v), [0.0, 1.0, 20.0])
    assert NoiseLevel(relative=0.1, relative_min=5.0).mode == "RELMIN"
    assert np.allclose(NoiseLevel(relative=0.1, relative_min=5.0).sigma(v), [5.0, 5.0, 20.0])
    assert NoiseLevel(correlation_days=0.0).rho(30.0) == 0.0
    assert NoiseLevel().rho(30.0) is None and NoiseLevel().sigma(v) is None
    q = QuantityNoise(relative=0.1, correlation_days=90.0,
                      wells={"A": NoiseLevel(absolute=2.0)})
    assert q.for_well("A").mode == "ABS" and q.for_well("A").correlation_days == 90.0
    assert q.for_well("B").mode == "REL"


def _case(tmp_path, noise: str, rows: list[str] | None = None):
    obs = tmp_path / "observed.csv"
    obs.write_text("\n".join(["well,days,quantity,value", *(rows or [
        "PRO-1,1.01,WOPR,100.0", "PRO-1,1.01,WBHP,224.0", "PRO-1,1.01,WGOR,66.2",
        "PRO-1,1.01,WWCT,0.0", "PRO-4,31.0,WOPR,100.0", "PRO-4,31.0,WBHP,223.9",
        "PRO-4,31.0,WWCT,0.0", "PRO-15,2936.0,WBHP,230.5"])]) + "\n")
    return write_case_toml(tmp_path / "case.toml", observed=obs, name="t",
                           history_end_days=None, extra=noise)


@requires_punq
@requires_opm
def test_the_case_file_noise_section_reaches_the_observation_set(tmp_path):
    case = load_case(_case(tmp_path, """
[noise.WBHP]
absolute = 2.5
[noise.WBHP.wells.PRO-4]
absolute = 1.5
"""))
    assert case.noise["WBHP"].for_well("PRO-4").absolute == 1.5
    rows = ObservationSet.from_case(case).rows
    bhp = rows[rows.quantity == "WBHP"].set_index("well").sigma
    assert bhp["PRO-1"] == 2.5 and bhp["PRO-4"] == 1.5 and bhp["PRO-15"] == 2.5


@requires_punq
@requires_opm
def test_bad_noise_values_are_refused_with_file_and_key_all_at_once(tmp_path):
    path = _case(tmp_path, """
[noise.WBHP]
absolute = 0.0
correlation_days = -5
[noise.WBHP.wells.PRO-44]
absolute = 1.0
[noise.WGOR]
absolute = 1.0
relative = 0.1
[noise.WWCT]
relative = 0.05
[noise.WOPR]
relative_min = 2.0
[noise.WBPH]
absolute = 1.0
[noise.WGPR]
relativ = 0.1
""")
    with pytest.raises(CaseError) as info:
        load_case(path)
    found = {p.where.split("key ")[-1].strip("'"): p for p in info.value.problems}
    assert all(str(path) in p.where for p in info.value.problems)
    assert "must be > 0" in found["noise.WBHP.absolute"].what
    assert ">= 0" in found["noise.WBHP.correlation_days"].what
    assert "did you mean 'PRO-4'" in found["noise.WBHP.wells.PRO-44"].what
    assert "not both" in found["noise.WGOR"].what
    assert "error of 0" in found["noise.WWCT"].what and "PRO-1" in found["noise.WWCT"].what
    assert "relative_min" in found["noise.WWCT"].fix
    assert "give relative too" in found["noise.WOPR"].what
    assert "did you mean 'WBHP'" in found["noise.WBPH"].what
    assert "did you mean 'relative'" in found["noise.WGPR.relativ"].fix
    assert len(info.value.problems) == 8


@requires_punq
@requires_opm
def test_check_prints_the_noise_the_fit_will_assume(tmp_path):
    """`hmflow check` ends on the noise table: per quantity, the level and where it comes from
    (stated in [noise], estimated from the data, ...)."""
    from typer.testing import CliRunner

    from hmflow.cli import app

    path = _case(tmp_path, """
[noise.WBHP]
absolute = 2.5
""")
    out = CliRunner().invoke(app, ["check", "--case", str(path)], env={"COLUMNS": "200"})
    assert out.exit_code == 0, out.output
    table = out.output[out.output.index("noise the fit assumes"):]
    bhp = [line for line in table.splitlines() if line.split()[:1] == ["WBHP"]]
    assert bhp and all("stated" in line and " 2.5 " in f"{line} " for line in bhp), table
    assert any(line.split()[:1] == ["WGOR"] for line in table.splitlines()), table


def test_whitening_is_the_ar1_recursion_along_each_series():
    """e_t = (z_t - rho z_(t-1)) / sqrt(1 - rho^2) within a well's series of one quantity, z_t
    itself at a series' first row, with a well's stated rho where it has one."""
    rng = np.random.default_rng(7)
    data = history(rng, wells=3).drop(columns="true")
    obs = ObservationSet.from_observed(
        data, 1600.0, noise={"WBHP": QuantityNoise(wells={"P2": NoiseLevel(
            correlation_days=60.0)})})
    z = rng.normal(size=len(obs.rows))
    for period in ("fit", "heldout"):
        idx = obs.vector_index(period)
        rows = obs.rows.iloc[idx]
        rhos = obs.row_rho(idx)
        series = rows.series.to_numpy()
        expected = []
        for k, i in enumerate(idx):
            first = k == 0 or series[k] != series[k - 1]
            rho = rhos[k]
            expected.append(z[i] if first or rho <= 0 else
                            (z[i] - rho * z[idx[k - 1]]) / math.sqrt(1 - rho * rho))
        assert np.array_equal(obs.whiten(z, period), np.array(expected))
        assert np.array_equal(obs.whiten(z, period), obs.whiten(z, period))  # cached
    assert len(set(np.round(obs.row_rho(obs.vector_index("fit")), 6))) > 2
