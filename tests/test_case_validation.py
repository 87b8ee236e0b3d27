"""Bad input gives one clear CaseError listing every problem, before any simulator time.

Small case directories are built in tmp_path; they reference the shared PUNQ-S3 deck by
absolute path, or a temp copy of its three files when the deck itself must be broken.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from conftest import (PUNQ_DECK, copy_punq_deck, requires_opm, requires_punq, sha256_file,
                      write_case_toml)
from hmcore.cases import load_case
from hmcore.errors import CaseError
from hmcore.model.observed import read_observed

pytestmark = [requires_punq, requires_opm]

HEADER = "well,days,quantity,value"
GOOD_ROWS = [  # a few real report days of PUNQ-S3 (values need not be the measured ones)
    "PRO-1,1.01,WOPR,100.0",
    "PRO-1,1.01,WBHP,224.0",
    "PRO-1,1.01,WGOR,66.2",
    "PRO-1,1.01,WWCT,0.0",
    "PRO-4,31.0,WOPR,100.0",
    "PRO-4,31.0,WBHP,223.9",
    "PRO-15,2936.0,WBHP,230.5",
]


def write_csv(path: Path, rows: list[str], header: str = HEADER) -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def make_case(tmp_path: Path, rows: list[str] | None = None, *, deck: Path = PUNQ_DECK,
              extra: str = "", extra_case: str = "", history_end_days: float | None = None) -> Path:
    obs = write_csv(tmp_path / "observed.csv", GOOD_ROWS if rows is None else rows)
    return write_case_toml(tmp_path / "case.toml", deck=deck, observed=obs, name="t",
                           history_end_days=history_end_days, extra=extra,
                           extra_case=extra_case)


def problems_of(case_path: Path) -> list:
    with pytest.raises(CaseError) as info:
        load_case(case_path)
    err = info.value
    # the exception text lists every problem (one line each) after a count
    assert str(err).startswith(f"{len(err.problems)} problem(s) found:")
    for p in err.problems:
        assert str(p) in str(err)
    return err.problems


def one_problem_matching(problems, *, where: str, what: str):
    hits = [p for p in problems if re.search(where, p.where) and re.search(what, p.what)]
    assert hits, f"no problem with where~{where!r} and what~{what!r} in {problems}"
    return hits[0]


def line_of(path: Path, pattern: str, after: str | None = None) -> int:
    """1-based line number of the first line matching ``pattern`` (after ``after``)."""
    lines = path.read_text().splitlines()
    start = 0
    if after is not None:
        start = next(i for i, l in enumerate(lines) if re.search(after, l)) + 1
    return next(i + 1 for i in range(start, len(lines)) if re.search(pattern, lines[i]))


# ----------------------------------------------------------------------------- good case
def test_good_case_loads(tmp_path):
    case = load_case(make_case(tmp_path))
    assert case.name == "t"
    assert set(case.info.wells) == {"PRO-1", "PRO-4", "PRO-5", "PRO-11", "PRO-12", "PRO-15"}
    assert len(case.observed[~case.observed.derived]) == len(GOOD_ROWS)
    assert case.space.names == ["poro_mult", "permx_mult", "permy_mult", "permz_mult", "skin"]


# ----------------------------------------------------------------------------- observed CSV
def test_unknown_well(tmp_path):
    rows = GOOD_ROWS + ["PRO-99,31.0,WBHP,222.0", "PRO-99,59.0,WBHP,221.0"]
    probs = problems_of(make_case(tmp_path, rows))
    assert len(probs) == 1
    p = one_problem_matching(probs, where=r"observed\.csv", what=r"unknown well 'PRO-99'")
    n = len(GOOD_ROWS)
    assert f"lines {n + 2}, {n + 3}" in p.where  # header is line 1
    assert "PRO-15" in p.fix  # lists the deck's wells


def test_unknown_quantity(tmp_path):
    probs = problems_of(make_case(tmp_path, GOOD_ROWS + ["PRO-1,31.0,WXYZ,1.0"]))
    p = one_problem_matching(probs, where=r"observed\.csv line %d$" % (len(GOOD_ROWS) + 2),
                             what=r"unknown quantity 'WXYZ'")
    assert "WBHP" in p.fix


@pytest.mark.parametrize("value", ["nan", "", "inf", "abc"])
def test_missing_or_nan_value(tmp_path, value):
    probs = problems_of(make_case(tmp_path, GOOD_ROWS + [f"PRO-1,31.0,WBHP,{value}"]))
    assert len(probs) == 1
    one_problem_matching(probs, where=r"observed\.csv line %d$" % (len(GOOD_ROWS) + 2),
                         what=r"value is missing, NaN or infinite")


def test_a_column_of_true_and_false_is_not_read_as_numbers(tmp_path):
    """pandas reads a column of TRUE/FALSE as booleans, which would pass as 1 and 0: a sigma
    or value of TRUE is not a number (hypothesis found sigma TRUE taken as 1.0)."""
    rows = [f"{r},TRUE" for r in GOOD_ROWS]
    probs = problems_of(write_case_toml(
        tmp_path / "case.toml", deck=PUNQ_DECK, name="t", history_end_days=None,
        observed=write_csv(tmp_path / "observed.csv", rows, HEADER + ",sigma")))
    assert len(probs) == len(GOOD_ROWS)
    one_problem_matching(probs, where=r"observed\.csv line 2$", what=r"sigma 'True' is not a number")
    rows = [GOOD_ROWS[0] + ",TRUE"] + [f"{r}," for r in GOOD_ROWS[1:]]  # with empty cells
    probs = problems_of(write_case_toml(
        tmp_path / "case.toml", deck=PUNQ_DECK, name="t", history_end_days=None,
        observed=write_csv(tmp_path / "observed.csv", rows, HEADER + ",sigma")))
    assert len(probs) == 1
    one_problem_matching(probs, where=r"observed\.csv line 2$", what=r"sigma 'True' is not a number")
    rows = [",".join(r.split(",")[:3] + ["TRUE"]) for r in GOOD_ROWS]
    probs = problems_of(make_case(tmp_path, rows))
    one_problem_matching(probs, where=r"observed\.csv line 2$",
                         what=r"value is missing, NaN or infinite")


@pytest.mark.parametrize("quantity", ["WOPR", "WWPR", "WGPR", "WGOR", "WWCT"])
def test_negative_rate(tmp_path, quantity):
    probs = problems_of(make_case(tmp_path, GOOD_ROWS + [f"PRO-1,31.0,{quantity},-5"]))
    p = one_problem_matching(probs, where=r"line %d$" % (len(GOOD_ROWS) + 2),
                             what=rf"negative {quantity} value -5")
    assert ">= 0" in p.fix


def test_out_of_range_water_cut_and_pressure(tmp_path):
    probs = problems_of(make_case(tmp_path, GOOD_ROWS + ["PRO-1,31.0,WWCT,1.5",
                                                         "PRO-1,31.0,WBHP,0"]))
    n = len(GOOD_ROWS)
    one_problem_matching(probs, where=rf"line {n + 2}$", what=r"water cut 1\.5 > 1")
    one_problem_matching(probs, where=rf"line {n + 3}$", what=r"non-positive pressure")


def test_duplicate_rows(tmp_path):
    # quantities are case-insensitive: 'wbhp' duplicates 'WBHP'
    rows = GOOD_ROWS + ["PRO-1,90.0,WBHP,220", "PRO-4,90.0,WBHP,219", "PRO-1,90.0,wbhp,221"]
    probs = problems_of(make_case(tmp_path, rows))
    n = len(GOOD_ROWS)
    p = one_problem_matching(probs, where=r"observed\.csv lines", what=r"duplicate rows")
    assert f"[{n + 2}, {n + 4}]" in p.where
    assert "PRO-1" in p.what and "WBHP" in p.what and "90" in p.what


def test_days_after_end_of_schedule(tmp_path):
    probs = problems_of(make_case(tmp_path, GOOD_ROWS + ["PRO-1,7000,WBHP,200"]))
    p = one_problem_matching(probs, where=r"observed\.csv lines? %d" % (len(GOOD_ROWS) + 2),
                             what=r"after the end of the schedule")
    assert "7000" in p.what and "6025" in p.what  # the schedule ends 1 Jul 1983 = day 6025


def test_day_on_last_report_step_is_accepted(tmp_path):
    load_case(make_case(tmp_path, GOOD_ROWS + ["PRO-1,6025,WBHP,200"]))


def test_negative_and_non_numeric_days(tmp_path):
    rows = GOOD_ROWS + ["PRO-1,-3,WBHP,200", "PRO-1,soon,WBHP,200"]
    probs = problems_of(make_case(tmp_path, rows))
    n = len(GOOD_ROWS)
    one_problem_matching(probs, where=rf"line {n + 2}$", what=r"days=-3.* negative")
    one_problem_matching(probs, where=rf"line {n + 3}$", what=r"days is not a number")


def test_missing_column_and_missing_file(tmp_path):
    csv = write_csv(tmp_path / "observed.csv", ["PRO-1,1.01,224.0"], header="well,days,value")
    probs = problems_of(write_case_toml(tmp_path / "case.toml", observed=csv, name="t"))
    one_problem_matching(probs, where=r"observed\.csv", what=r"missing column\(s\) \['quantity'\]")
    probs = problems_of(write_case_toml(tmp_path / "case.toml", observed=tmp_path / "nope.csv",
                                        name="t"))
    one_problem_matching(probs, where=r"nope\.csv", what=r"observed history file not found")


# ----------------------------------------------------------------------------- TOML
def test_low_greater_than_high_in_parameters(tmp_path):
    extra = """
[[parameters]]
name = "poro"
kind = "multiply"
keywords = ["PORO"]
low = 2.0
high = 1.0
"""
    probs = problems_of(make_case(tmp_path, extra=extra))
    p = one_problem_matching(probs, where=r"case\.toml key 'parameters\.0'", what=r"low < high")
    assert "low=2.0" in p.what and "high=1.0" in p.what and "'poro'" in p.what


def test_unknown_key_in_toml(tmp_path):
    probs = problems_of(make_case(tmp_path, extra_case="tolerance = 3",
                                  extra="[simulatr]\nbackend = 'opm'"))
    p = one_problem_matching(probs, where=r"case\.toml key 'case\.tolerance'", what=r"[Ee]xtra")
    assert "spelling" in p.fix
    one_problem_matching(probs, where=r"key 'simulatr'", what=r"[Ee]xtra")


def test_invalid_toml_syntax(tmp_path):
    path = tmp_path / "case.toml"
    path.write_text("[case]\nname = \"t\"\ndeck = \n")
    probs = problems_of(path)
    one_problem_matching(probs, where=r"case\.toml", what=r"invalid TOML.*line 3")


def test_parameters_checked_against_the_deck(tmp_path):
    extra = """
[[parameters]]
name = "skin_far"
kind = "skin"
wells = ["PRO-99"]
layers = [9]
low = 0
high = 10
"""
    probs = problems_of(make_case(tmp_path, extra=extra))
    one_problem_matching(probs, where=r"skin_far", what=r"unknown well\(s\) \['PRO-99'\]")
    one_problem_matching(probs, where=r"skin_far", what=r"layer\(s\) \[9\] outside 1\.\.5")


def test_history_end_after_schedule(tmp_path):
    probs = problems_of(make_case(tmp_path, history_end_days=9000))
    one_problem_matching(probs, where=r"key 'case\.history_end_days'", what=r"after the end")


# ----------------------------------------------------------------------------- deck
def test_missing_include_file(tmp_path):
    deck = copy_punq_deck(tmp_path / "deck")
    (tmp_path / "deck" / "PUNQS3.PRP").unlink()
    probs = problems_of(make_case(tmp_path, deck=deck))
    p = one_problem_matching(probs, where=re.escape(str(deck)),
                             what=r"INCLUDE file 'PUNQS3\.PRP' not found")
    include_line = line_of(deck, r"^INCLUDE", after=r"truth-case PORO")
    assert p.where.endswith(f"line {include_line}")


def test_deck_opm_cannot_parse(tmp_path):
    deck = copy_punq_deck(tmp_path / "deck")
    text = deck.read_text()
    assert "   19    28      5 /" in text
    deck.write_text(text.replace("   19    28      5 /", "   19  abc  5 /"))
    probs = problems_of(make_case(tmp_path, deck=deck))
    p = one_problem_matching(probs, where=re.escape(str(deck)), what=r"OPM cannot parse the deck")
    assert "DIMENS" in p.what and "abc" in p.what
    assert f"line {line_of(deck, r'^DIMENS')}" in p.what


def test_missing_deck_file(tmp_path):
    probs = problems_of(make_case(tmp_path, deck=tmp_path / "NOPE.DATA"))
    one_problem_matching(probs, where=r"NOPE\.DATA", what=r"deck file not found")


# regression: the lexer used to split quoted paths at "/" (INCLUDE 'sub/file' was "not found")
def test_deck_with_include_in_a_subdirectory_is_accepted(tmp_path):
    deck = copy_punq_deck(tmp_path / "deck")
    (tmp_path / "deck" / "include").mkdir()
    (tmp_path / "deck" / "PUNQS3.PRP").rename(tmp_path / "deck" / "include" / "PUNQS3.PRP")
    deck.write_text(deck.read_text().replace("'PUNQS3.PRP'", "'include/PUNQS3.PRP'"))
    case = load_case(make_case(tmp_path, deck=deck))
    assert "PORO" in case.info.properties


# ----------------------------------------------------------------------------- all at once
def test_several_problems_are_all_reported(tmp_path):
    deck = copy_punq_deck(tmp_path / "deck")
    (tmp_path / "deck" / "PUNQS3.GEO").unlink()
    rows = GOOD_ROWS + [
        "PRO-1,31.0,WXYZ,1.0",     # unknown quantity
        "PRO-1,59.0,WBHP,nan",     # NaN
        "PRO-1,59.0,WOPR,-5",      # negative rate
        "PRO-4,90.0,WBHP,220",     # duplicate ...
        "PRO-4,90.0,WBHP,221",     # ... rows
    ]
    probs = problems_of(make_case(tmp_path, rows, deck=deck))
    n = len(GOOD_ROWS)
    one_problem_matching(probs, where=r"PUNQS3\.DATA line", what=r"'PUNQS3\.GEO' not found")
    one_problem_matching(probs, where=rf"line {n + 2}$", what=r"unknown quantity")
    one_problem_matching(probs, where=rf"line {n + 3}$", what=r"NaN")
    one_problem_matching(probs, where=rf"line {n + 4}$", what=r"negative WOPR")
    one_problem_matching(probs, where=rf"lines \[{n + 5}, {n + 6}\]", what=r"duplicate")
    assert len(probs) == 5


# regression: read_observed() used to raise before the deck-dependent checks ran
def test_csv_problems_and_deck_dependent_problems_are_reported_together(tmp_path):
    rows = GOOD_ROWS + ["PRO-1,59.0,WBHP,nan", "PRO-99,31.0,WBHP,222.0", "PRO-1,7000,WBHP,200"]
    probs = problems_of(make_case(tmp_path, rows))
    one_problem_matching(probs, where=r"observed\.csv", what=r"NaN")
    one_problem_matching(probs, where=r"observed\.csv", what=r"unknown well 'PRO-99'")
    one_problem_matching(probs, where=r"observed\.csv", what=r"after the end of the schedule")


# regression: a TOML schema error used to hide the deck and history problems
def test_toml_problems_and_csv_problems_are_reported_together(tmp_path):
    probs = problems_of(make_case(tmp_path, GOOD_ROWS + ["PRO-1,59.0,WBHP,nan"],
                                  extra_case="tolerance = 3"))
    one_problem_matching(probs, where=r"key 'case\.tolerance'", what=r"[Ee]xtra")
    one_problem_matching(probs, where=r"observed\.csv", what=r"NaN")


# ----------------------------------------------------------------------------- derivation
def test_water_and_gas_rates_are_derived_by_hand(tmp_path):
    csv = write_csv(tmp_path / "obs.csv", [
        "PRO-1,31.0,WOPR,150",
        "PRO-1,31.0,WWCT,0.2",
        "PRO-1,31.0,WGOR,80",
        "PRO-1,59.0,WOPR,100",      # no WWCT/WGOR on this day: nothing derived
        "PRO-4,31.0,WOPR,120",
        "PRO-4,31.0,WWCT,0.5",
        "PRO-4,31.0,WWPR,999",      # PRO-4 has a measured WWPR: never derived for PRO-4
        "PRO-4,31.0,WGOR,0",
    ])
    obs = read_observed(csv)
    derived = obs[obs.derived].set_index(["well", "days", "quantity"])["value"]
    # PRO-1 day 31: WWPR = WOPR * WWCT / (1 - WWCT) = 150 * 0.2 / 0.8 = 37.5 sm3/d
    #               WGPR = WOPR * WGOR = 150 * 80 = 12000 sm3/d
    # PRO-4 day 31: WGPR = 120 * 0 = 0; its WWPR is the measured 999
    assert derived.to_dict() == pytest.approx({("PRO-1", 31.0, "WWPR"): 37.5,
                                               ("PRO-1", 31.0, "WGPR"): 12000.0,
                                               ("PRO-4", 31.0, "WGPR"): 0.0})
    rows = obs[obs.derived]
    assert (rows.line == -1).all() and rows.sigma.isna().all()
    measured = obs[~obs.derived]
    assert len(measured) == 8
    pro4_wwpr = measured[(measured.well == "PRO-4") & (measured.quantity == "WWPR")]
    assert pro4_wwpr["value"].item() == 999


def test_derived_rates_reach_the_case(tmp_path):
    rows = ["PRO-5,31.0,WOPR,200", "PRO-5,31.0,WWCT,0.25", "PRO-5,31.0,WGOR,70"]
    case = load_case(make_case(tmp_path, rows))
    d = case.observed[case.observed.derived].set_index("quantity")["value"]
    # 200 * 0.25 / 0.75 = 66.666..., 200 * 70 = 14000
    assert d["WWPR"] == pytest.approx(200 * 0.25 / 0.75)
    assert d["WGPR"] == pytest.approx(14000.0)


def test_flowing_flag_is_read(tmp_path):
    csv = write_csv(tmp_path / "obs.csv", ["PRO-1,366,WBHP,230,0", "PRO-1,31,WBHP,220,1",
                                           "PRO-1,59,WBHP,219,"],
                    header="well,days,quantity,value,flowing")
    obs = read_observed(csv).set_index("days")["flowing"]
    assert not obs[366.0] and obs[31.0] and obs[59.0]


# ----------------------------------------------------------------------------- CLI
def _cli(args: list[str]):
    from hmflow.cli import app

    result = CliRunner().invoke(app, args, env={"COLUMNS": "400", "NO_COLOR": "1"})
    text = " ".join(result.output.split())  # undo any wrapping
    return result, text


def test_cli_check_bad_case_exits_2_and_prints_every_problem(tmp_path):
    rows = GOOD_ROWS + ["PRO-1,31.0,WXYZ,1.0", "PRO-1,59.0,WBHP,nan", "PRO-1,59.0,WOPR,-5"]
    case = make_case(tmp_path, rows)
    result, text = _cli(["check", "--case", str(case)])
    assert result.exit_code == 2, result.output
    assert "3 problem(s)" in text
    n = len(GOOD_ROWS)
    for line, what in [(n + 2, "unknown quantity 'WXYZ'"), (n + 3, "value is missing, NaN"),
                       (n + 4, "negative WOPR value -5")]:
        assert f"observed.csv line {line}" in text and what in text


def test_cli_check_good_case_exits_0(tmp_path):
    case = make_case(tmp_path)
    result, text = _cli(["check", "--case", str(case)])
    assert result.exit_code == 0, result.output
    assert "OK case t" in text
    assert "19x28x5" in text and "1761 active cells" in text


def test_cli_check_missing_case_file(tmp_path):
    result, text = _cli(["check", "--case", str(tmp_path / "nope.toml")])
    assert result.exit_code == 2
    assert "case file not found" in text


@pytest.fixture
def no_simulator(monkeypatch):
    """Make every way to start a simulation fail the test (and record the attempt)."""
    import hmcore.scoring.evaluation
    import hmcore.simulation.simulator

    calls = []

    def forbidden(*args, **kwargs):
        calls.append(args)
        pytest.fail("the simulator must not be called for an invalid case")

    monkeypatch.setattr(hmcore.simulation.simulator, "_run_process", forbidden)
    monkeypatch.setattr(hmcore.simulation.simulator, "make_simulator", forbidden)
    monkeypatch.setattr(hmcore.scoring.evaluation, "evaluate", forbidden)
    monkeypatch.setattr(hmcore.scoring.evaluation, "prepare_run_deck", forbidden)
    return calls


def test_cli_evaluate_bad_case_exits_2_without_simulating(tmp_path, no_simulator):
    case = make_case(tmp_path, GOOD_ROWS + ["PRO-99,31.0,WBHP,222.0"])
    out = tmp_path / "out"
    result, text = _cli(["evaluate", "--case", str(case), "--set", "skin=5", "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "unknown well 'PRO-99'" in text
    assert no_simulator == []
    assert not out.exists()  # nothing written for an invalid case


def test_cli_evaluate_bad_set_exits_2_without_simulating(tmp_path, no_simulator):
    case = make_case(tmp_path)
    out = tmp_path / "out"
    result, text = _cli(["evaluate", "--case", str(case), "--set", "skinn=5", "--set", "skin=abc",
                         "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert "unknown parameter 'skinn'" in text and "'abc' is not a number" in text
    assert no_simulator == []


def test_validation_does_not_touch_the_deck(tmp_path):
    deck = copy_punq_deck(tmp_path / "deck")
    before = {p.name: sha256_file(p) for p in (tmp_path / "deck").iterdir()}
    load_case(make_case(tmp_path, deck=deck))
    assert {p.name: sha256_file(p) for p in (tmp_path / "deck").iterdir()} == before


def test_observed_quantity_missing_from_the_summary_section_is_reported(tmp_path):
    deck = copy_punq_deck(tmp_path / "deck")
    text = deck.read_text()
    assert "\nWBHP\n/\n" in text
    deck.write_text(text.replace("\nWBHP\n/\n", "\n"))
    probs = problems_of(make_case(tmp_path, deck=deck))  # GOOD_ROWS hold WBHP rows
    one_problem_matching(probs, where=r"observed\.csv|PUNQS3\.DATA", what=r"WBHP")


# ----------------------------------------------------------------------------- issue 16
def _aquct(item: int = 4, match: str | None = None, kind: str = "item_multiply",
           keyword: str = "AQUCT") -> str:
    return (f'[[parameters]]\nname = "aq"\nkind = "{kind}"\nkeywords = ["{keyword}"]\n'
            f'item = {item}\nlow = 0.5\nhigh = 2.0\n' + (f'match = "{match}"\n' if match else ""))


def test_history_end_before_the_first_observation_is_refused(tmp_path):
    probs = problems_of(make_case(tmp_path, history_end_days=0.5))
    p = one_problem_matching(probs, where=r"key 'case\.history_end_days'",
                             what=r"before the first observation \(day 1\.01\).*no observed row")
    assert "1.01" in p.fix


@pytest.mark.parametrize("value, says", [("true", "valid number"), ("inf", "finite number"),
                                         ("nan", "finite number"), ('"30"', "valid number")])
def test_time_tolerance_must_be_a_finite_number(tmp_path, value, says):
    probs = problems_of(make_case(tmp_path, extra_case=f"time_tolerance_days = {value}"))
    one_problem_matching(probs, where=r"key 'case\.time_tolerance_days'", what=says)


def test_a_mistyped_key_gets_did_you_mean(tmp_path):
    probs = problems_of(make_case(tmp_path, extra_case="histroy_end_day = 100",
                                  extra="[simulator]\ntimout_s = 5"))
    assert "did you mean 'history_end_days'" in one_problem_matching(
        probs, where=r"case\.histroy_end_day'", what=r"[Ee]xtra").fix
    assert "did you mean 'timeout_s'" in one_problem_matching(
        probs, where=r"simulator\.timout_s'", what=r"[Ee]xtra").fix


@pytest.mark.parametrize("backend, says", [
    ("nosuch-simulator {deck}", r"program 'nosuch-simulator' is not found"),
    ("true {deck} {rundir}", r"unknown placeholder \{rundir\}.*did you mean 'run_dir'"),
    ("true '{deck}", r"cannot be split into words"),
    ("true --out={run_dir}", r"does not name the deck"),
    ("bin/flow {deck}", r"relative path"),
])
def test_a_simulator_command_that_cannot_run_is_refused(tmp_path, backend, says):
    import json

    probs = problems_of(make_case(tmp_path, extra=f"[simulator]\nbackend = {json.dumps(backend)}"))
    one_problem_matching(probs, where=r"key 'simulator\.backend'", what=says)


def test_empty_and_duplicate_parameter_lists_are_problems_not_tracebacks(tmp_path):
    case = make_case(tmp_path)
    case.write_text("parameters = []\n" + case.read_text())
    one_problem_matching(problems_of(case), where=r"key 'parameters'", what=r"list is empty")
    twice = '[[parameters]]\nname = "s"\nkind = "skin"\nlow = 0\nhigh = 5\n'
    probs = problems_of(make_case(tmp_path, extra=twice + twice))
    one_problem_matching(probs, where=r"key 'parameters'", what=r"\['s'\] are given more")


def test_item_multiply_on_aquct_is_checked_record_by_record(tmp_path):
    assert load_case(make_case(tmp_path, extra=_aquct(4))).space.names == ["aq"]
    one_problem_matching(problems_of(make_case(tmp_path, extra=_aquct(4, match="7"))),
                         where=r"\[\[parameters\]\] 'aq'",
                         what=r"match = '7' selects no AQUCT record.*\['1', '2'\]")
    one_problem_matching(problems_of(make_case(tmp_path, extra=_aquct(12))),
                         where=r"'aq'", what=r"11 item\(s\), no item 12")
    one_problem_matching(problems_of(make_case(tmp_path, extra=_aquct(4, keyword="AQUFETP"))),
                         where=r"'aq'", what=r"no AQUFETP keyword")


def test_relperm_on_a_column_that_is_no_relative_permeability_is_refused(tmp_path):
    probs = problems_of(make_case(tmp_path, extra=_aquct(4, kind="relperm", keyword="SWOF")))
    one_problem_matching(probs, where=r"parameters\.0", what=r"item 4 of SWOF is not a "
                         r"relative permeability column; use item = 2 or 3")


def test_table_multiply_scales_a_fluid_table_and_names_the_column_and_table(tmp_path):
    """RSVD item 2 (the initial dissolved gas) is scaled row by row; column 1 (the depth) and
    a table the deck lacks are refused with the columns and the tables it has."""
    from hmcore.model.run_deck import prepare_run_deck

    case = load_case(make_case(tmp_path, extra=_aquct(2, kind="table_multiply", keyword="RSVD")))
    deck = prepare_run_deck(case.deck, {"aq": 0.5}, case.space, tmp_path / "run",
                            case.info).read_text()
    rsvd = deck[deck.index("\nRSVD\n"):].split("/")[0].split()
    assert [float(x) for x in rsvd[-4:]] == [2175.0, 37.0, 2496.0, 37.0]  # 74 x 0.5, depths kept
    from hmcore.eclipse.deck_info import _parse

    run_deck = tmp_path / "run" / case.deck.name
    assert list(_parse(run_deck)[0]["RSVD"][0][0].get_raw_data_list()) == [2175, 37, 2496, 37]
    one_problem_matching(problems_of(make_case(tmp_path, extra=_aquct(
        1, kind="table_multiply", keyword="RSVD"))), where=r"parameters\.0",
        what=r"table_multiply needs item = 2 for RSVD")
    one_problem_matching(problems_of(make_case(tmp_path, extra=_aquct(
        2, kind="table_multiply", keyword="PVDO"))), where=r"'aq'",
        what=r"no PVDO table, so the table_multiply parameter acts on nothing")
    one_problem_matching(problems_of(make_case(tmp_path, extra=_aquct(
        2, kind="table_multiply", keyword="RSVD") + 'mode = "power"\n')),
        where=r"parameters\.0", what=r"mode = 'power' is only for kind 'relperm'")


def test_a_parameter_that_changes_nothing_in_the_deck_is_refused(tmp_path):
    extra = ('[[parameters]]\nname = "skin_top"\nkind = "skin"\nwells = ["PRO-1"]\n'
             'layers = [1]\nlow = 0\nhigh = 5\n')  # PRO-1 has no connection in layer 1
    probs = problems_of(make_case(tmp_path, extra=extra))
    one_problem_matching(probs, where=r"'skin_top'", what=r"deck text is the same at low=0 "
                         r"and high=5: this skin parameter changes nothing")


def test_an_include_cycle_is_refused_at_once(tmp_path):
    deck = copy_punq_deck(tmp_path / "deck")
    text = deck.read_text()
    grid_inc = tmp_path / "deck" / "loop.inc"
    grid_inc.write_text("INCLUDE\n 'PUNQS3.DATA' /\n")
    deck.write_text(text.replace("\nPROPS", "\nINCLUDE\n 'loop.inc' /\n\nPROPS", 1))
    probs = problems_of(make_case(tmp_path, deck=deck))
    one_problem_matching(probs, where=re.escape(str(grid_inc)) + " line 1",
                         what=r"makes a cycle \(PUNQS3\.DATA -> loop\.inc -> PUNQS3\.DATA\)")


@pytest.mark.parametrize("row, says", [
    ("PRO-1,31.0,WBHP,223.9,abc,1", r"sigma 'abc' is not a number"),
    ("PRO-1,31.0,WBHP,223.9,inf,1", r"sigma=inf is not finite"),
    ("PRO-1,31.0,WBHP,223.9,None,1", r"sigma 'None' is not a number"),  # found by hypothesis
    ("PRO-1,31.0,WBHP,223.9,,maybe", r"flowing 'maybe' is not a yes/no value"),
    (",31.0,WBHP,223.9,,1", r"the well is empty"),
    ("PRO1,31.0,WBHP,223.9,,1", r"unknown well 'PRO1' \(did you mean 'PRO-1'\?\)"),
    ("PRO-1,31.0,WBHPP,223.9,,1", r"unknown quantity 'WBHPP' \(did you mean 'WBHP'\?\)"),
])
def test_observed_cells_that_are_not_what_they_must_be(tmp_path, row, says):
    rows = [r + ",,1" for r in GOOD_ROWS] + [row]
    write_csv(tmp_path / "observed.csv", rows, header=HEADER + ",sigma,flowing")
    case = write_case_toml(tmp_path / "case.toml", deck=PUNQ_DECK,
                           observed=tmp_path / "observed.csv", name="t",
                           history_end_days=None)
    one_problem_matching(problems_of(case), where=rf"observed\.csv line {len(rows) + 1}$",
                         what=says)


def test_user_errors_in_paths_are_problems_not_tracebacks(tmp_path):
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00[case]\n")
    one_problem_matching(problems_of(binary), where=r"binary\.toml", what=r"not a text file")
    with pytest.raises(CaseError, match="null byte"):
        load_case("a\x00b.toml")
    with pytest.raises(CaseError, match="folder, not a case file"):
        load_case(tmp_path)
    case = make_case(tmp_path)
    case.write_text(case.read_text().replace(str(PUNQ_DECK), "~nosuchuser/PUNQS3.DATA"))
    one_problem_matching(problems_of(case), where=r"key 'case\.deck'",
                         what=r"cannot be expanded")
