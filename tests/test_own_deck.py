"""Bringing a field's own deck: ``hmflow init`` from WCONHIST/WCONINJH, units, injectors,
history-controlled rates, limits relative to the deck, fault parameters.

SPE9 (``../shared/spe9``, read in place) is turned into a history-matching deck by
``benchmarks/make_spe9_history.py`` once per session (one real OPM Flow run for its truth).
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from hmcore.cases import load_case
from hmcore.errors import CaseError
from hmcore.units import convert, factor_to_deck
from hmflow.cli import app
from tests.conftest import PUNQ_DECK, PUNQ_OBS_FULL, write_case_toml

REPO = Path(__file__).resolve().parents[1]
SPE9 = REPO.parent / "shared" / "spe9" / "SPE9.DATA"
needs_spe9 = pytest.mark.skipif(not SPE9.is_file(), reason=f"SPE9 deck not found at {SPE9}")


def hmflow_cli(args: list[str]):
    """``hmflow ARGS`` in this process, 400 columns wide: a message naming a long temporary
    path is not folded into the middle of a word (a check reads it as one line)."""
    return CliRunner().invoke(app, args, env={"COLUMNS": "400"})


@pytest.fixture(scope="module")
def spe9_history(tmp_path_factory) -> Path:
    """The SPE9 history-matching deck (WCONHIST per producer, WCONINJH for INJE1)."""
    if not SPE9.is_file():
        pytest.skip(f"SPE9 deck not found at {SPE9}")
    out = tmp_path_factory.mktemp("spe9") / "history"
    subprocess.run([sys.executable, str(REPO / "benchmarks" / "make_spe9_history.py"),
                    "--out", str(out)], check=True, timeout=900, capture_output=True)
    return out / "SPE9_HM.DATA"


@pytest.fixture(scope="module")
def spe9_case(spe9_history, tmp_path_factory) -> Path:
    where = tmp_path_factory.mktemp("spe9-case")
    out = hmflow_cli(["init", "--deck", str(spe9_history),
                                   "--out", str(where / "spe9.toml")])
    assert out.exit_code == 0, out.output
    return where / "spe9.toml"


# ----------------------------------------------------------------------------- units
def test_units_convert_and_refuse_by_name():
    assert factor_to_deck("WBHP", "psia", "METRIC") == pytest.approx(0.0689475729, rel=1e-9)
    assert factor_to_deck("WBHP", "bar", "FIELD") == pytest.approx(14.503773773, rel=1e-9)
    assert convert(np.array([1000.0]), "WOPR", "stb/day", "METRIC")[0] == pytest.approx(158.987, rel=1e-5)
    assert factor_to_deck("WGPR", "Mscf/d", "METRIC") == pytest.approx(28.316846592, rel=1e-9)
    assert factor_to_deck("WWCT", "%", "FIELD") == 0.01
    with pytest.raises(ValueError, match="gauge"):
        factor_to_deck("WBHP", "psig", "METRIC")
    with pytest.raises(ValueError, match="'bar' is a pressure unit.*reports WOPR in stb/day"):
        factor_to_deck("WOPR", "bar", "FIELD")
    with pytest.raises(ValueError, match="unknown unit 'furlongs'"):
        factor_to_deck("WBHP", "furlongs", "FIELD")


def test_psi_column_is_converted_into_a_metric_deck(tmp_path):
    obs = pd.read_csv(PUNQ_OBS_FULL)
    bhp = obs.quantity == "WBHP"
    psi = obs.copy()
    psi.loc[bhp, "value"] = psi.loc[bhp, "value"] * 14.503773773
    psi["units"] = np.where(bhp, "psia", "")
    psi.to_csv(tmp_path / "obs_psi.csv", index=False)
    case = load_case(write_case_toml(tmp_path / "c.toml", observed=tmp_path / "obs_psi.csv"))
    ref = load_case(write_case_toml(tmp_path / "r.toml"))
    a = case.observed[case.observed.quantity == "WBHP"].value.to_numpy()
    b = ref.observed[ref.observed.quantity == "WBHP"].value.to_numpy()
    np.testing.assert_allclose(a, b, rtol=1e-9)


def test_wrong_units_are_refused_with_file_lines_and_the_deck_unit(tmp_path):
    obs = pd.read_csv(PUNQ_OBS_FULL).head(20)
    obs["units"] = ""
    obs.loc[obs.quantity == "WBHP", "units"] = "psig"
    obs.loc[obs.quantity == "WOPR", "units"] = "bar"
    obs.to_csv(tmp_path / "obs.csv", index=False)
    with pytest.raises(CaseError) as err:
        load_case(write_case_toml(tmp_path / "c.toml", observed=tmp_path / "obs.csv"))
    text = str(err.value)
    assert "obs.csv line" in text
    assert "gauge pressure 'psig'" in text and "write WBHP in bar" in text
    assert "'bar' is a pressure unit, not a liquid rate" in text and "sm3/day" in text


# ----------------------------------------------------------------------------- init
@needs_spe9
def test_init_on_spe9_reads_wconhist_with_units_and_passes_check(spe9_history, spe9_case):
    case = load_case(spe9_case)  # what `hmflow check` runs
    assert case.info.unit_system == "FIELD"
    obs = pd.read_csv(spe9_case.with_name("spe9_observed.csv"))
    # the first WCONHIST record of PRODU2, as written in the deck, is the day-10 observation
    text = spe9_history.read_text()
    text = text[text.index("WCONHIST"):]
    first = next(line for line in text.splitlines() if line.strip().startswith("'PRODU2'"))
    tokens = first.split()
    oil, water, gas, bhp = float(tokens[3]), float(tokens[4]), float(tokens[5]), float(tokens[9])
    day10 = obs[(obs.well == "PRODU2") & (obs.days == 10)].set_index("quantity")
    assert day10.loc["WOPR", "value"] == pytest.approx(oil, rel=1e-5)
    assert day10.loc["WWPR", "value"] == pytest.approx(water, rel=1e-5, abs=1e-9)
    assert day10.loc["WGPR", "value"] == pytest.approx(gas, rel=1e-5)
    assert day10.loc["WBHP", "value"] == pytest.approx(bhp, rel=1e-5)
    assert day10.loc["WOPR", "units"] == "stb/day" and day10.loc["WGPR", "units"] == "mscf/day"
    assert day10.loc["WBHP", "units"] == "psia"
    assert set(obs[obs.well == "INJE1"].quantity) == {"WWIR", "WBHP"}
    # ORAT control fixes the oil rate, RATE control the injected rate: out of the misfit
    fixed = case.observed[case.observed.controlled]
    assert set(fixed.quantity) == {"WOPR", "WWIR"}
    assert set(case.fit_observed.quantity) == {"WBHP", "WWPR", "WGPR"}
    toml = spe9_case.read_text()
    assert "# injectors (1): INJE1" in toml and '# name = "skin_PRODU12"' in toml


@needs_spe9
def test_init_never_overwrites(spe9_history, spe9_case):
    before = spe9_case.read_text()
    out = hmflow_cli(["init", "--deck", str(spe9_history), "--out", str(spe9_case)])
    assert out.exit_code == 2 and "never overwrites" in " ".join(out.output.split())
    assert spe9_case.read_text() == before


def test_init_on_punqs3_without_history_says_what_to_give_then_works_with_a_csv(tmp_path):
    runner = CliRunner()
    out = runner.invoke(app, ["init", "--deck", str(PUNQ_DECK), "--out", str(tmp_path / "p.toml")])
    assert out.exit_code == 2
    said = " ".join(out.output.split())
    assert "no measured history" in said and "--observed" in said
    assert not (tmp_path / "p.toml").exists()
    out = runner.invoke(app, ["init", "--deck", str(PUNQ_DECK), "--observed", str(PUNQ_OBS_FULL),
                              "--out", str(tmp_path / "p.toml")])
    assert out.exit_code == 0, out.output
    case = load_case(tmp_path / "p.toml")
    assert case.space.names == ["poro_mult", "permx_mult", "permy_mult", "permz_mult", "skin"]
    assert len(case.observed) == len(load_case(write_case_toml(tmp_path / "r.toml")).observed)


# ----------------------------------------------------------------------------- parameters
def test_fault_and_well_parameters_naming_nothing_in_the_deck_are_refused(tmp_path):
    extra = """
[[parameters]]
name = "f1"
kind = "fault"
faults = ["F_NORTH"]
low = 0.0
high = 1.0

[[parameters]]
name = "skin_x"
kind = "skin"
wells = ["PRO-99"]
low = -2.0
high = 10.0
"""
    with pytest.raises(CaseError) as err:
        load_case(write_case_toml(tmp_path / "c.toml", extra=extra))
    text = str(err.value)
    assert "unknown fault(s) ['F_NORTH']" in text and "FAULTS keyword" in text
    assert "unknown well(s) ['PRO-99']" in text


def test_fault_multiplier_is_written_as_multflt_that_opm_reads(tmp_path):
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.model.parameters import Parameter, ParameterSpace
    from tests.conftest import copy_punq_deck

    deck = copy_punq_deck(tmp_path / "deck")
    text = deck.read_text()
    grid_end = text.index("\nPROPS")
    fault = "\nFAULTS\n 'F_MID' 10 10 1 28 1 5 'X' /\n/\n"
    deck.write_text(text[:grid_end] + fault + text[grid_end:])
    info = DeckInfo.inspect(deck)
    assert info.faults == ("F_MID",)
    space = ParameterSpace(parameters=(Parameter(name="f", kind="fault", faults=("F_MID",),
                                                 low=0.0, high=1.0),))
    run_deck = prepare_run_deck(deck, {"f": 0.05}, space, tmp_path / "run", info)
    assert "MULTFLT\n 'F_MID' 0.05 /" in run_deck.read_text()
    DeckInfo.inspect(run_deck)  # OPM's parser takes it


@needs_spe9
def test_spe9_permeability_x3_is_not_invalid(spe9_case):
    from hmcore.scoring.physics import check_physics

    case = load_case(spe9_case)
    values = {"poro_mult": 1.0, "permx_mult": 3.0, "permy_mult": 3.0, "permz_mult": 3.0,
              "skin": 0.0}
    phys = check_physics(values, case.space, case.info, case.physics)
    assert phys.valid, phys.violations
    # the cap is relative to the deck: SPE9 reaches about 10 D, so 20 D would have fired
    assert case.info.properties["PERMX"][1] * 3 > 20000


@pytest.mark.opm
@needs_spe9
def test_spe9_injector_rate_and_bhp_are_matched(spe9_case, tmp_path):
    from hmcore.scoring.evaluation import evaluate, score_responses

    case = load_case(spe9_case)
    truth = {"poro_mult": 1.0, "permx_mult": 1.8, "permy_mult": 1.8, "permz_mult": 0.6,
             "skin": 0.0}
    ev = evaluate(case, truth, tmp_path / "run")
    assert ev.status.value == "COMPLETE", ev.reason
    s = score_responses(case, ev.responses)
    # the injector's BHP is in E; its rate, fixed by the RATE control, is not
    assert set(s["per_well_response"]["INJE1"]) == {"bhp"}
    assert s["per_well_response"]["INJE1"]["bhp"] < 0.05
    from hmcore.scoring.alignment import align

    pairs = align(case.observed, ev.responses, case.time_tolerance_days).pairs
    inje = pairs[pairs.well == "INJE1"]
    assert set(inje.quantity) == {"WWIR", "WBHP"}
    wwir = inje[inje.quantity == "WWIR"]
    # under RATE control the simulated rate is the measured one (up to the deck's 6 digits)
    np.testing.assert_allclose(wwir.simulated, wwir.observed, rtol=1e-3)
    assert ev.E < 0.01  # the truth's globals: only the noise and the hidden skin remain


def test_a_stray_slash_that_opm_flow_tolerates_is_a_warning_not_an_error(tmp_path):
    from tests.conftest import copy_punq_deck

    deck = copy_punq_deck(tmp_path / "deck")
    text = deck.read_text()
    deck.write_text(text.replace("\nSCHEDULE", "\nSCHEDULE\nTUNING\n/\n/\n/\n/", 1))
    out = hmflow_cli(["check", "--case", str(write_case_toml(tmp_path / "c.toml",
                                                                          deck=deck))])
    said = " ".join(out.output.split())
    assert out.exit_code == 0, said
    assert "warning OPM Flow tolerates this and runs on" in said
    assert "PUNQS3.DATA line" in said and "Extra line starting with '/'" in said


def _punq_with_multnum(tmp_path: Path) -> Path:
    """PUNQ-S3 with MULTNUM in GRID: layers 1-2 region 1, layers 3-5 region 2."""
    from tests.conftest import copy_punq_deck

    deck = copy_punq_deck(tmp_path / "deck")
    text = deck.read_text()
    grid_end = text.index("\nPROPS")
    per_layer = 19 * 28
    multnum = f"\nMULTNUM\n {2 * per_layer}*1 {3 * per_layer}*2 /\n"
    deck.write_text(text[:grid_end] + multnum + text[grid_end:])
    return deck


def test_region_multiplier_becomes_multireg_and_lands_in_its_region(tmp_path):
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo, _parse
    from hmcore.model.parameters import Parameter, ParameterSpace
    from hmcore.scoring.physics import check_physics
    from hmcore.model.case import PhysicsSettings

    deck = _punq_with_multnum(tmp_path)
    info = DeckInfo.inspect(deck)
    assert info.regions["MULTNUM"] == (1, 2) and "MULTNUM" in info.grid_keywords
    space = ParameterSpace(parameters=(
        Parameter(name="k2", kind="multiply", keywords=("PERMX",), region="MULTNUM",
                  region_numbers=(2,), low=0.1, high=10.0),
        Parameter(name="t12", kind="multregt", region_numbers=(1, 2), low=0.0, high=1.0)))
    run_deck = prepare_run_deck(deck, {"k2": 2.5, "t12": 0.1}, space, tmp_path / "run", info)
    text = run_deck.read_text()
    assert "MULTIREG\n 'PERMX' 2.5 2 'M' /" in text
    assert "MULTREGT\n 1 2 0.1 'XYZ' 'ALL' 'M' /" in text
    _, base, _, _ = _parse(deck)
    _, moved, _, _ = _parse(run_deck)
    k0 = np.asarray(base.field_props().get_double_array("PERMX"))
    k1 = np.asarray(moved.field_props().get_double_array("PERMX"))
    region = np.asarray(base.field_props().get_int_array("MULTNUM"))
    np.testing.assert_allclose(k1[region == 2], 2.5 * k0[region == 2], rtol=1e-9)
    np.testing.assert_allclose(k1[region == 1], k0[region == 1], rtol=1e-12)
    # the physics checks see the factor in region 2 only
    factors = info.cells.factors([("PERMX", 2.5, ("MULTNUM", (2,)))])["PERMX"]
    assert set(np.unique(factors)) == {1.0, 2.5}
    assert check_physics({"k2": 2.5, "t12": 0.1}, space, info, PhysicsSettings()).runnable


def test_region_parameters_naming_a_missing_region_are_refused(tmp_path):
    deck = _punq_with_multnum(tmp_path)
    extra = """
[[parameters]]
name = "k7"
kind = "multiply"
keywords = ["PERMX"]
region = "MULTNUM"
region_numbers = [7]
low = 0.5
high = 2.0

[[parameters]]
name = "kf"
kind = "multiply"
keywords = ["PORO"]
region = "OPERNUM"
region_numbers = [1]
low = 0.5
high = 2.0
"""
    with pytest.raises(CaseError) as err:
        load_case(write_case_toml(tmp_path / "c.toml", deck=deck, extra=extra))
    text = str(err.value)
    assert "MULTNUM has no region(s) [7]" in text and "values are [1, 2]" in text
    assert "GRID section defines no OPERNUM" in text


def test_dates_are_accepted_where_days_are(tmp_path):
    obs = pd.read_csv(PUNQ_OBS_FULL)
    start = pd.Timestamp("1967-01-01")
    dated = obs.drop(columns=["days"]).assign(
        date=[(start + pd.Timedelta(days=float(d))).date().isoformat() for d in obs.days])
    dated.to_csv(tmp_path / "dated.csv", index=False)
    case = load_case(write_case_toml(tmp_path / "c.toml", observed=tmp_path / "dated.csv",
                                     history_end_days=None,
                                     extra_case="history_end_days = 1975-01-15"))
    ref = load_case(write_case_toml(tmp_path / "r.toml"))
    np.testing.assert_allclose(np.sort(case.observed.days), np.sort(ref.observed.days), atol=1.0)
    assert case.history_end_days == ref.history_end_days == 2936.0
    clash = obs.assign(date="1967-02-01").head(3)
    clash.to_csv(tmp_path / "clash.csv", index=False)
    with pytest.raises(CaseError, match="but date 1967-02-01 is day 31 from the deck's START"):
        load_case(write_case_toml(tmp_path / "x.toml", observed=tmp_path / "clash.csv"))


def test_init_commented_parameters_load_when_switched_on(tmp_path):
    """Every block `init` writes commented out (per-well skins, per-region permeability,
    aquifer strength) is a valid parameter of this deck once its '# ' is removed."""
    from hmcore.model.case_init import starting_case, write_starting_case

    deck = _punq_with_multnum(tmp_path)
    start = starting_case(deck, "p", PUNQ_OBS_FULL)
    case_path, _ = write_starting_case(start, tmp_path / "p.toml", PUNQ_OBS_FULL)
    head, tail = case_path.read_text().split("# More parameters", 1)
    tail = "\n".join(line[2:] if line.startswith("# ") else "" for line in tail.splitlines()[1:])
    (tmp_path / "all.toml").write_text(head + tail)
    case = load_case(tmp_path / "all.toml")
    assert {"perm_multnum_1", "perm_multnum_2", "aquct_mult", "skin_PRO-11"} <= set(case.space.names)
    assert len(case.space.names) == 5 + 6 + 2 + 1 + 2  # + SWCR (SWFN), SGCR (SGFN) shifts


@pytest.mark.opm
def test_stopping_at_the_last_observation_gives_the_same_misfit(tmp_path):
    from hmcore.scoring.evaluation import evaluate
    from hmcore.simulation.responses import last_time

    obs = pd.read_csv(PUNQ_OBS_FULL)
    obs[obs.days <= 1500].to_csv(tmp_path / "early.csv", index=False)
    full = load_case(write_case_toml(tmp_path / "full.toml", observed=tmp_path / "early.csv",
                                     history_end_days=None))
    short = load_case(write_case_toml(tmp_path / "short.toml", observed=tmp_path / "early.csv",
                                      history_end_days=None,
                                      extra="[simulator]\nstop_at_last_observation = true"))
    assert full.stop_step is None and short.stop_step is not None
    assert short.observed.days.max() <= short.run_end_days < full.run_end_days
    values = {"poro_mult": 1.1, "permx_mult": 1.4, "permy_mult": 1.4, "permz_mult": 0.8,
              "skin": 3.0}
    a = evaluate(full, values, tmp_path / "a")
    b = evaluate(short, values, tmp_path / "b")
    assert a.status.value == b.status.value == "COMPLETE", (a.reason, b.reason)
    assert b.E == pytest.approx(a.E, rel=1e-6)
    assert last_time(Path(b.run_dir) / "PUNQS3.SMSPEC") == pytest.approx(short.run_end_days)


@pytest.mark.opm
def test_wpimult_follows_every_compdat_of_its_well_and_changes_the_run(tmp_path):
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.model.parameters import Parameter, ParameterSpace
    from hmcore.simulation.responses import read_responses
    from hmcore.simulation.simulator import OpmFlow

    info = DeckInfo.inspect(PUNQ_DECK)
    space = ParameterSpace(parameters=(Parameter(name="pi4", kind="wpimult", wells=("PRO-4",),
                                                 low=0.1, high=10.0),))
    runs = {}
    for value in (1.0, 0.2):
        run_deck = prepare_run_deck(PUNQ_DECK, {"pi4": value}, space, tmp_path / f"r{value}", info)
        text = run_deck.read_text()
        assert text.count("\nCOMPDAT") == text.count("\nWPIMULT") == 1  # PUNQ-S3: one COMPDAT
        assert text.index("\nWPIMULT\n 'PRO-4' ") > text.index("\nCOMPDAT")
        result = OpmFlow().run(run_deck, tmp_path / f"r{value}")
        r = read_responses(result.summary_path, ["PRO-4", "PRO-1"])
        runs[value] = r.set_index(["well", "quantity", "days"]).value
    bhp4 = runs[0.2].loc["PRO-4", "WBHP"]
    base4 = runs[1.0].loc["PRO-4", "WBHP"]
    assert (bhp4 < base4 - 1.0).any()  # a fifth of the PI: the well draws down harder


@pytest.mark.opm
def test_a_dated_wpimult_changes_the_run_only_from_its_day(tmp_path):
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.errors import CaseError
    from hmcore.model.parameters import Parameter, ParameterSpace
    from hmcore.simulation.responses import read_responses
    from hmcore.simulation.simulator import OpmFlow

    info = DeckInfo.inspect(PUNQ_DECK)
    days = info.report_days
    n = next(n for n in range(len(days) // 2, len(days)) if days[n] - days[n - 1] > 10)
    day = days[n]
    dated = Parameter(name="pi4", kind="wpimult", wells=("PRO-4",), low=0.1, high=10.0,
                      start_day=day - 3.0)  # between report steps: from the next one
    runs = {}
    for value in (1.0, 0.2):
        run_deck = prepare_run_deck(PUNQ_DECK, {"pi4": value}, ParameterSpace(parameters=(dated,)),
                                    tmp_path / f"r{value}", info)
        text = run_deck.read_text()
        # once, in the schedule at the step that reaches the day, not after the COMPDAT
        assert text.count("\nWPIMULT\n") == 1
        assert text.index("\nWPIMULT\n 'PRO-4' ") > text.index("\nCOMPDAT")
        assert f"from day {day:g}" in text
        result = OpmFlow().run(run_deck, tmp_path / f"r{value}")
        assert result.summary_path is not None, result
        r = read_responses(result.summary_path, ["PRO-4"])
        runs[value] = r[r.quantity == "WBHP"].set_index("days").value
    diff = (runs[0.2] - runs[1.0]).abs()
    assert diff[diff.index < day - 1].max() < 1e-6 * runs[1.0].abs().max()  # nothing before
    assert diff[diff.index >= day].max() > 1.0  # a fifth of the PI from that day: harder drawdown
    late = Parameter(name="pi4", kind="wpimult", wells=("PRO-4",), low=0.1, high=10.0,
                     start_day=info.end_days + 10)
    with pytest.raises(CaseError, match="after the schedule's last report step"):
        prepare_run_deck(PUNQ_DECK, {"pi4": 0.5}, ParameterSpace(parameters=(late,)),
                         tmp_path / "late", info)
    with pytest.raises(ValueError, match="start_day .* only for kind 'wpimult'"):
        Parameter(name="s", kind="skin", low=0.0, high=5.0, start_day=100.0)


def test_a_dated_wpimult_waits_for_a_well_completed_later(tmp_path):
    """PROD4 completed after the change's day: the WPIMULT at that day names only the wells
    completed by then (OPM refuses an unknown connection set), and PROD4 gets the factor
    after its own COMPDAT; the written deck parses (no simulation)."""
    pytest.importorskip("opm.io")
    import re

    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.scenarios.hidden import synthetic_deck_info
    from hmcore.model.parameters import Parameter, ParameterSpace

    base = synthetic_deck_info(0, tmp_path / "base").path.read_text()
    prod4 = "".join(re.findall(r"^ 'PROD4' 12 17 .*\n", base, flags=re.M))
    assert prod4.count("\n") == 4
    late = base.replace(prod4, "").replace(" 1 'MAR' 2020 /\n/\n", " 1 'MAR' 2020 /\n/\n\n"
                                           "COMPDAT\n" + prod4 + "/\n", 1)
    (tmp_path / "late").mkdir()
    (tmp_path / "late" / "LATE.DATA").write_text(late)
    info = DeckInfo.inspect(tmp_path / "late" / "LATE.DATA")
    space = ParameterSpace(parameters=tuple(
        Parameter(name=f"pi_{w}", kind="wpimult", wells=(w,), low=0.1, high=10.0,
                  start_day=10.0) for w in ("PROD1", "PROD4")))
    deck = prepare_run_deck(info.path, {"pi_PROD1": 0.5, "pi_PROD4": 0.25}, space,
                            tmp_path / "run", info)
    text = deck.read_text()
    at_day = text.index("-- productivity multipliers from day 31 added by hmflow")
    block = text[at_day:text.index("/\n", text.index("WPIMULT", at_day))]
    assert "'PROD1' 0.5" in block and "PROD4" not in block
    after = text[text.index("COMPDAT", at_day):]  # PROD4's own COMPDAT, then its factor
    assert re.search(r"WPIMULT\n 'PROD4' 0.25 12 17 1 /", after), after[:600]
    DeckInfo.inspect(deck)  # OPM parses what was written


@pytest.mark.opm
def test_init_imports_a_summary_file(tmp_path):
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.model.parameters import ParameterSpace
    from hmcore.simulation.responses import read_responses
    from hmcore.simulation.simulator import OpmFlow

    info = DeckInfo.inspect(PUNQ_DECK)
    run_deck = prepare_run_deck(PUNQ_DECK, {}, ParameterSpace.reference(), tmp_path / "run", info)
    # the simulator also writes the RSM text summary (RUNSUM, SEPARATE), as Eclipse does
    run_deck.write_text(re.sub(r"^SUMMARY\b.*$", lambda m: m.group(0) + "\nRUNSUM\nSEPARATE\n",
                               run_deck.read_text(), count=1, flags=re.M))
    smspec = OpmFlow().run(run_deck, tmp_path / "run").summary_path
    for summary, out_name in ((smspec, "p"), (smspec.with_suffix(".RSM"), "r")):
        out = hmflow_cli(["init", "--deck", str(PUNQ_DECK), "--summary",
                                       str(summary), "--out", str(tmp_path / out_name / "p.toml")])
        assert out.exit_code == 0, out.output
    case = load_case(tmp_path / "p" / "p.toml")
    assert set(case.observed.well) == set(info.wells)
    sim = read_responses(smspec, ["PRO-1"])
    want = sim[(sim.quantity == "WBHP") & (sim.days > 0) & (sim.value > 0)].value.to_numpy()
    got = case.observed[(case.observed.well == "PRO-1") & (case.observed.quantity == "WBHP")]
    np.testing.assert_allclose(got.sort_values("days").value.to_numpy(), want, rtol=1e-5)
    # the RSM gives the same rows and values (to its 7 significant digits)
    binary, text = (pd.read_csv(tmp_path / d / "p_observed.csv") for d in ("p", "r"))
    keys = ["well", "quantity", "days"]
    both = binary.merge(text, on=keys, how="outer", suffixes=("_b", "_r"), indicator=True)
    assert len(binary) > 2000 and (both._merge == "both").all()
    np.testing.assert_allclose(both.value_r, both.value_b, rtol=2e-5, atol=1e-6)
    assert (both.units_r == both.units_b).all()


RSM_FIELD = """\
1
 ------------------------------------------------------------------------------------
 SUMMARY OF RUN FIELD EXPORT
 ------------------------------------------------------------------------------------
 DATE         WOPRH        WBHPH        WGPRH        WWCTH
              STB/DAY      PSIA         MSCF/DAY
              *10**3
              PRO-1        PRO-1        PRO-1        PRO-1

 ------------------------------------------------------------------------------------
 1-FEB-1967      0.2000       3500.0       120.0        0.00
 1-MAR-1967      0.2100       3450.0       125.0        0.01
 1-JLY-1967      0.1900       3300.0       130.0        0.05
"""


def test_rsm_export_in_field_units_with_dates_is_converted_into_the_metric_deck(tmp_path):
    """A production-database export as RSM: DATE column, FIELD units, a *10**3 multiplier,
    history vectors; PUNQ-S3 is METRIC, so rates and pressures are converted."""
    rsm = tmp_path / "export.RSM"
    rsm.write_text(RSM_FIELD)
    out = hmflow_cli(["init", "--deck", str(PUNQ_DECK), "--summary", str(rsm),
                                   "--out", str(tmp_path / "c" / "p.toml")])
    assert out.exit_code == 0, out.output
    obs = pd.read_csv(tmp_path / "c" / "p_observed.csv")
    oil = obs[obs.quantity == "WOPR"].sort_values("days")
    assert oil.days.tolist() == [31.0, 59.0, 181.0]          # 1-JLY-1967 is day 181
    np.testing.assert_allclose(oil.value, np.array([200.0, 210.0, 190.0]) * 0.158987294928,
                               rtol=1e-5)  # written to 6 significant digits
    bhp = obs[obs.quantity == "WBHP"].sort_values("days")
    np.testing.assert_allclose(bhp.value.iloc[0], 3500.0 * 0.0689475729, rtol=1e-5)
    assert set(obs.units) == {"sm3/day", "bar", "fraction"}


def test_a_broken_rsm_is_refused_with_every_line_named(tmp_path):
    rsm = tmp_path / "bad.RSM"
    rsm.write_text(RSM_FIELD.replace("*10**3", "x1000  ").replace("0.2100", "n/a")
                   .replace(" 1-JLY-1967", " 1-XYZ-1967"))
    out = hmflow_cli(["init", "--deck", str(PUNQ_DECK), "--summary", str(rsm),
                                   "--out", str(tmp_path / "c" / "p.toml")])
    assert out.exit_code == 2 and not (tmp_path / "c").exists()
    text = " ".join(out.output.split())
    assert "bad.RSM:7" in text and "multiplier 'x1000' is not *10**N" in text
    assert "bad.RSM:12" in text and "'n/a' is not a number" in text
    assert "bad.RSM:13" in text and "DATE '1-XYZ-1967' is not a date" in text
    rsm.write_text(RSM_FIELD[:RSM_FIELD.index(" 1-FEB")])  # a header and no row
    out = hmflow_cli(["init", "--deck", str(PUNQ_DECK), "--summary", str(rsm),
                                   "--out", str(tmp_path / "c" / "p.toml")])
    assert out.exit_code == 2 and "holds no data row" in " ".join(out.output.split())
    rsm.write_text(RSM_FIELD.replace("PSIA", "PSIG"))
    out = hmflow_cli(["init", "--deck", str(PUNQ_DECK), "--summary", str(rsm),
                                   "--out", str(tmp_path / "c" / "p.toml")])
    assert out.exit_code == 2 and "gauge pressure" in " ".join(out.output.split())


def test_relperm_endpoint_shift_moves_the_critical_saturation():
    from hmcore.model.run_deck import shift_endpoint

    sw = np.array([0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 1.0])
    krw = np.array([0, 0, 0.01, 0.05, 0.1, 0.2, 0.35, 0.5, 1.0])
    up = shift_endpoint(sw, krw, 0.1)          # SWCR 0.25 -> 0.35
    assert up[sw <= 0.35].max() == 0 and up[sw > 0.35].min() > 0
    assert up[-1] == 1.0 and np.all(np.diff(up) >= 0)
    down = shift_endpoint(sw, krw, -0.05)      # SWCR 0.25 -> 0.20
    assert down[1] > 0
    krow = np.array([1.0, 0.8, 0.6, 0.4, 0.2, 0.1, 0.02, 0, 0])
    more = shift_endpoint(sw, krow, 0.1)       # SOWCR 0.2 -> 0.3: krow is 0 from Sw 0.7
    assert more[sw >= 0.7].max() == 0 and more[0] == 1.0 and np.all(np.diff(more) <= 0)
    connate = np.array([0.02, 0.03, 0.05, 0.1, 0.2, 0.3, 0.4, 0.6, 1.0])  # no zero row
    assert np.array_equal(shift_endpoint(sw, connate, 0.0), connate)  # no shift: unchanged


def test_relperm_endpoint_parameter_writes_a_table_opm_reads(tmp_path):
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo, _parse
    from hmcore.model.parameters import Parameter, ParameterSpace

    info = DeckInfo.inspect(PUNQ_DECK)
    space = ParameterSpace(parameters=(Parameter(name="swcr_shift", kind="relperm",
                                                 keywords=("SWFN",), item=2, mode="endpoint",
                                                 low=-0.1, high=0.2),))
    run_deck = prepare_run_deck(PUNQ_DECK, {"swcr_shift": 0.15}, space, tmp_path / "run", info)
    deck, _, _, _ = _parse(run_deck)
    table = np.array(deck["SWFN"][0][0].get_raw_data_list()).reshape(-1, 3)
    base = np.array(_parse(PUNQ_DECK)[0]["SWFN"][0][0].get_raw_data_list()).reshape(-1, 3)
    crit = lambda t: t[np.flatnonzero(t[:, 1] <= 0)[-1], 0]  # noqa: E731
    assert crit(table) > crit(base)
    assert table[-1, 1] == pytest.approx(base[-1, 1])


def test_wpimult_does_not_compound_on_a_well_completed_twice(tmp_path):
    """PRO-4's layer 4 moved to a second COMPDAT later in the schedule: every connection of
    the well gets the factor once (a whole-well WPIMULT after each COMPDAT would give 0.25)."""
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo, _parse
    from hmcore.model.parameters import Parameter, ParameterSpace
    from tests.conftest import copy_punq_deck

    deck = copy_punq_deck(tmp_path / "deck")
    text = deck.read_text().replace("'PRO-4'     9   17   4   4   'OPEN'   2*  0.15  1*  5.0 /\n",
                                    "", 1)
    first_dates = text.index("\nDATES", text.index("COMPDAT"))
    second = "\nCOMPDAT\n'PRO-4'     9   17   4   4   'OPEN'   2*  0.15  1*  5.0 /\n/\n"
    deck.write_text(text[:first_dates] + "\nTSTEP\n 1 /\n" + second + text[first_dates:])
    info = DeckInfo.inspect(deck)
    space = ParameterSpace(parameters=(Parameter(name="pi4", kind="wpimult", wells=("PRO-4",),
                                                 low=0.1, high=10.0),))
    run_deck = prepare_run_deck(deck, {"pi4": 0.5}, space, tmp_path / "run", info)
    _, _, base, _ = _parse(deck)
    _, _, moved, _ = _parse(run_deck)
    last = len(base.reportsteps) - 1
    cf0 = {c.k: c.cf for c in base.get_well("PRO-4", last).connections()}
    cf1 = {c.k: c.cf for c in moved.get_well("PRO-4", last).connections()}
    assert set(cf0) == {3, 4}  # 0-based k of layers 4 and 5
    for k in cf0:
        assert cf1[k] == pytest.approx(0.5 * cf0[k], rel=1e-9)


def _spe9_deck_with(tmp_path: Path, schedule: str) -> Path:
    """SPE9's deck up to its schedule (producers only), then ``schedule``."""
    text = SPE9.read_text()
    head = text[:text.index("WCONINJE")]
    head = re.sub(r"INCLUDE\s*\n\s*'?([A-Za-z0-9_.]+)'?\s*/",
                  lambda m: f"INCLUDE\n  '{SPE9.parent / m.group(1)}' /", head)
    head = "\n".join(line for line in head.splitlines() if "'INJE1'" not in line)
    deck = tmp_path / "HIST.DATA"
    deck.write_text(head + "\n" + schedule + "\nEND\n")
    return deck


@needs_spe9
def test_history_reads_wildcards_defaults_welopen_and_the_end_of_history(tmp_path):
    from hmcore.eclipse.deck_info import DeckInfo

    deck = _spe9_deck_with(tmp_path, """
WCONHIST
 'PRODU*' 'OPEN' 'ORAT' 1000 1* 2000 1* 1* 1* 3000 /
/
TSTEP
 2*10 /
WELOPEN
 'PRODU2' 'SHUT' /
/
TSTEP
 10 /
WELOPEN
 'PRODU2' 'OPEN' /
/
WLIST
 '*LIST' 'NEW' 'PRODU3' 'PRODU4' 'PRODU5' /
 '*LIST' 'DEL' 'PRODU4' /
 '*OTHER' 'MOV' 'PRODU5' /
 '*OTHER' 'ADD' 'PRODU6' /
 '*NEST' 'NEW' '*OTHER' /
/
WCONHIST
 '*LIST' 'OPEN' 'ORAT' 5 /
 '*OTHER' 'OPEN' 'ORAT' 7 /
 '*NEST' 'OPEN' 'ORAT' 9 /
/
TSTEP
 10 /
WCONPROD
 '*' 'OPEN' 'ORAT' 100 4* 1000 /
/
TSTEP
 10 /
""")
    info = DeckInfo.inspect(deck)
    table = info.history.observed_table()
    p2 = table[table.well == "PRODU2"].pivot_table(index="days", columns="quantity",
                                                    values="value")
    assert list(p2.index) == [10.0, 20.0, 40.0]  # shut over (20, 30]; prediction after day 40
    assert (p2.WWPR == 0).all() and (p2.WOPR == 1000).all() and (p2.WBHP == 3000).all()
    assert set(table.well) == {f"PRODU{n}" for n in range(2, 27)}
    assert table.days.max() == 40.0
    # well lists as WLIST left them: *LIST = PRODU3 (PRODU4 deleted, PRODU5 moved to *OTHER);
    # *NEST = the wells of *OTHER (PRODU5, PRODU6), as OPM's Schedule reads it
    last = table[table.days == 40.0].pivot_table(index="well", columns="quantity",
                                                 values="value")
    assert last.WOPR[["PRODU3", "PRODU4", "PRODU5", "PRODU6"]].tolist() == [5, 1000, 9, 9]
    assert not any("well list" in s for s in info.history.skipped)


def test_time_zones_and_eclipse_months_in_dates():
    from hmcore.model.observed import parse_dates

    got = parse_dates(pd.Series(["2015-01-21T00:00:00Z", "2015-01-21T02:00:00+02:00",
                                 "1 JLY 2015", "21-jan-2015", "31/01/2015"]))
    assert list(got[:4].dt.strftime("%Y-%m-%d")) == ["2015-01-21", "2015-01-21", "2015-07-01",
                                                     "2015-01-21"]
    assert pd.isna(got[4])


RSM_TIME = """\
1
 ----------------------------------------------------------
 SUMMARY OF RUN LAB EXPORT
 ----------------------------------------------------------
 TIME         WOPRH
 HOURS        SCC/HR
              PRO-1

 ----------------------------------------------------------
 24.0         5.0
 48.0         6.0
"""


def test_rsm_time_column_honours_its_unit_and_a_file_without_the_leading_space(tmp_path):
    """TIME in HOURS is read as days; a TIME unit that is no time is refused by line; a
    file written without Eclipse's leading space is read with the same column offset."""
    from hmcore.errors import CaseError
    from hmcore.simulation.rsm import read_rsm

    rsm = tmp_path / "lab.RSM"
    rsm.write_text(RSM_TIME)
    got = read_rsm(rsm)
    np.testing.assert_allclose(got.days, [1.0, 2.0])
    np.testing.assert_allclose(got["WOPRH:PRO-1"], [5.0, 6.0])
    rsm.write_text("\n".join(line[1:] if line.startswith(" ") else line
                             for line in RSM_TIME.splitlines()))
    np.testing.assert_allclose(read_rsm(rsm).days, [1.0, 2.0])
    rsm.write_text(RSM_TIME.replace("HOURS", "YEARS"))
    with pytest.raises(CaseError) as err:
        read_rsm(rsm)
    assert "lab.RSM:10" in str(err.value) and "expected DAYS or HOURS" in str(err.value)
