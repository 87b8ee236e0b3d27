"""The embedded synthetic case: deterministic generation, a deck OPM reads, a truth with
information in every response, noise as documented, and a truth the deck editor reproduces.

Runs OPM Flow for real (three single-threaded runs of a few seconds each, one at a time).
"""

from __future__ import annotations

import hashlib
import json
import shutil
import threading
import time
import tomllib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import SIMULATION_SLOTS, requires_opm

from hmcore.scenarios import synthetic as syn
from hmcore.scenarios import synthetic_deck as syn_deck
from hmcore.scoring import noise
from hmcore.model.parameters import Parameter, ParameterSpace
from hmcore.simulation.simulator import OpmFlow, SimulationResult

pytestmark = [requires_opm, pytest.mark.opm]

FILES = (syn.DECK_NAME, syn.OBSERVED_NAME, syn.TRUTH_NAME, syn.TRUTH_RESPONSES_NAME,
         syn.CASE_NAME)


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("hmflow-cache")


@pytest.fixture(scope="module")
def case_dir(cache_root: Path) -> Path:
    """The seed-0 case written through ensure_synthetic_case into a private cache."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(syn.CACHE_ENV, str(cache_root))
        with SIMULATION_SLOTS:
            case = syn.ensure_synthetic_case(0)
    assert case == cache_root / "synthetic-v1-seed0" / "case.toml"
    return case.parent


@pytest.fixture(scope="module")
def truth(case_dir: Path) -> pd.DataFrame:
    return pd.read_csv(case_dir / syn.TRUTH_RESPONSES_NAME)


@pytest.fixture(scope="module")
def observed(case_dir: Path) -> pd.DataFrame:
    return pd.read_csv(case_dir / syn.OBSERVED_NAME)


def _series(df: pd.DataFrame, well: str, quantity: str) -> pd.Series:
    sub = df[(df.well == well) & (df.quantity == quantity)].sort_values("days")
    return pd.Series(sub["value"].to_numpy(), index=sub["days"].to_numpy())


# ------------------------------------------------------------------------------ files
def test_case_files_and_case_toml(case_dir: Path) -> None:
    for name in FILES:
        assert (case_dir / name).is_file(), name
    cfg = tomllib.loads((case_dir / syn.CASE_NAME).read_text())["case"]
    assert cfg["name"] == "synthetic" and cfg["deck"] == "SYNTH.DATA"
    assert cfg["observed"] == "observed.csv" and cfg["time_tolerance_days"] == 30
    end = syn_deck.report_steps()[-1].days
    assert 0.7 * end <= cfg["history_end_days"] <= 0.8 * end
    meta = json.loads((case_dir / syn.TRUTH_NAME).read_text())
    assert meta["parameters"] == syn.SYNTHETIC_TRUTH and meta["seed"] == 0
    assert meta["generator_version"] == syn_deck.GENERATOR_VERSION and "noise" in meta
    assert not ParameterSpace.reference().check_in_bounds(syn.SYNTHETIC_TRUTH)


def test_ensure_reuses_the_cache(case_dir: Path, cache_root: Path,
                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(syn.CACHE_ENV, str(cache_root))

    def must_not_run(*args, **kwargs):
        raise AssertionError("the cached case was regenerated")

    monkeypatch.setattr(syn, "write_synthetic_case", must_not_run)
    assert syn.ensure_synthetic_case(0) == case_dir / syn.CASE_NAME
    assert not [p for p in cache_root.iterdir() if p.name.startswith(".")]  # no temp leftovers


def test_ensure_is_atomic_when_generation_fails(tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(syn.CACHE_ENV, str(tmp_path))

    def half_write(dest: Path, seed: int = 0, **kwargs) -> Path:
        (Path(dest) / syn.DECK_NAME).write_text("partial")
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(syn, "write_synthetic_case", half_write)
    with pytest.raises(RuntimeError, match="simulated crash"):
        syn.ensure_synthetic_case(7)
    assert list(tmp_path.iterdir()) == []  # nothing half-written is left behind
    assert syn.synthetic_case_dir(7) == tmp_path / "synthetic-v1-seed7"


def test_ensure_writes_the_case_once_for_callers_at_the_same_time(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two callers at once (as two pytest-xdist workers at collection): one writes the case,
    the other waits for it and returns it; no lock file or temporary folder is left."""
    monkeypatch.setenv(syn.CACHE_ENV, str(tmp_path))
    writes: list[Path] = []
    both = threading.Barrier(2)

    def slow_write(dest: Path, seed: int = 0, **kwargs) -> Path:
        writes.append(Path(dest))
        time.sleep(1.0)  # the other caller reaches the lock meanwhile
        for name in FILES:
            (Path(dest) / name).write_text(f"seed {seed}\n")
        return Path(dest) / syn.CASE_NAME

    def call(_) -> Path:
        both.wait(timeout=30)
        return syn.ensure_synthetic_case(5)

    monkeypatch.setattr(syn, "write_synthetic_case", slow_write)
    with ThreadPoolExecutor(2) as pool:
        cases = list(pool.map(call, range(2)))
    assert cases == [tmp_path / "synthetic-v1-seed5" / syn.CASE_NAME] * 2
    assert len(writes) == 1, writes
    assert [p.name for p in tmp_path.iterdir()] == ["synthetic-v1-seed5"]


def test_same_seed_gives_identical_files(case_dir: Path, tmp_path: Path) -> None:
    with SIMULATION_SLOTS:
        again = syn.write_synthetic_case(tmp_path / "again", 0).parent
    for name in FILES:
        assert (again / name).read_bytes() == (case_dir / name).read_bytes(), name


def test_fields_depend_only_on_the_seed() -> None:
    def fields(seed: int) -> syn_deck.SyntheticFields:
        return syn_deck.make_fields(np.random.default_rng(seed).spawn(2)[0])

    a, b, c = fields(0), fields(0), fields(1)
    for name in ("poro", "permx", "permz"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
        assert not np.allclose(getattr(a, name), getattr(c, name))
    assert syn_deck.render_deck(a, 0) == syn_deck.render_deck(b, 0) != syn_deck.render_deck(c, 1)
    # layered log-normal field, porosity tied to log-perm
    logk = np.log(a.permx)
    means = np.exp(logk.mean(axis=(1, 2)))
    assert np.argmin(means) == 4 and np.argmax(means) == 1
    assert np.corrcoef(logk.ravel(), a.poro.ravel())[0, 1] > 0.6
    assert np.all((a.poro > 0.04) & (a.poro < 0.36)) and np.all(a.permz < a.permx)


BUILT_IN_DECK_SHA256 = "551e3d302f0d4ba1973b50e8414396b7f94e17f424928c39f721944f0e241520"
"""SYNTH.DATA of seed 0 as synthetic-v1 writes it (its figures are published): a change to the
generator that changes it must bump GENERATOR_VERSION."""


def test_the_built_in_deck_is_unchanged_by_the_layouts() -> None:
    """The layouts are options: the default renders the seed-0 deck byte for byte as before."""
    field_rng, _ = np.random.default_rng(0).spawn(2)
    deck = syn_deck.render_deck(syn_deck.make_fields(field_rng), 0)
    assert syn_deck.GENERATOR_VERSION == "synthetic-v1"
    assert hashlib.sha256(deck.encode()).hexdigest() == BUILT_IN_DECK_SHA256
    assert syn_deck.render_deck(syn_deck.make_fields(np.random.default_rng(0).spawn(2)[0],
                                                     syn_deck.DEFAULT_LAYOUT),
                                0, syn_deck.DEFAULT_LAYOUT) == deck


def test_the_small_layout_keeps_the_wells_shut_ins_and_breakthroughs(small_case: Path) -> None:
    """SMALL_LAYOUT, as the session's small case (conftest.small_case): 10 x 10 x 5 cells over
    3 years, the same four producers on rate control, a shut-in after the history end, gas
    breakthrough in the crestal wells and water in a flank well, its own case name."""
    layout = syn_deck.SMALL_LAYOUT
    folder = small_case.parent
    cfg = tomllib.loads(small_case.read_text())["case"]
    assert cfg["name"] == "synthetic-small" and cfg["deck"] == syn.DECK_NAME
    assert cfg["history_end_days"] == syn_deck.default_history_end_days(layout)
    meta = json.loads((folder / syn.TRUTH_NAME).read_text())
    assert meta["layout"] == {"name": "small", "cells": [10, 10, 5], "cell_size_m": 200.0,
                              "years": 3}
    assert meta["parameters"] == syn.SYNTHETIC_TRUTH
    deck = (folder / syn.DECK_NAME).read_text()
    assert "\nDIMENS\n 10 10 5 /" in deck and "small layout" in deck.splitlines()[0]
    assert [w.name for w in layout.wells] == [w.name for w in syn.WELLS]
    steps = syn_deck.report_steps(layout)
    assert len(steps) == 12 * 3 + 3 and steps[-1].days == 1096.0
    assert any(not s.open_wells and s.days > cfg["history_end_days"] for s in steps)
    bt = meta["breakthrough_days"]
    assert bt["PROD1"]["gas_days"] and bt["PROD2"]["gas_days"]
    assert any(bt[w]["water_days"] for w in ("PROD3", "PROD4"))
    observed = pd.read_csv(folder / syn.OBSERVED_NAME)
    assert sorted(observed.well.unique()) == sorted(w.name for w in layout.wells)
    shut = observed[(observed.quantity == "WBHP") & (observed.flowing == 0)]
    assert shut.well.nunique() == 4 and shut.days.nunique() == 3


# ------------------------------------------------------------------------------ deck
def test_deck_parses_and_is_editable(case_dir: Path) -> None:
    from opm.io.ecl_state import EclipseState
    from opm.io.parser import ParseContext, Parser

    deck_path = case_dir / syn.DECK_NAME
    deck = Parser().parse(str(deck_path), ParseContext())
    names = {kw.name for kw in deck}
    for kw in ("OIL", "WATER", "GAS", "DISGAS", "METRIC", "TOPS", "PORO", "PERMX", "PERMZ",
               "COPY", "AQUFETP", "AQUANCON", "EQUIL", "RPTONLY", "WCONPROD", "COMPDAT",
               "WELTARG", "FOPT", "FWPT", "FGPT", "FPR"):
        assert kw in names, kw
    state = EclipseState(deck)
    props = state.field_props()
    assert np.array_equal(props.get_double_array("PERMX"), props.get_double_array("PERMY"))
    tops = np.asarray(deck["TOPS"].get_raw_array())
    assert tops.size == syn_deck.NX * syn_deck.NY * syn_deck.NZ and np.ptp(tops) > 50.0  # a real structure

    lines = deck_path.read_text().splitlines()
    for section in ("RUNSPEC", "GRID", "PROPS", "REGIONS", "SOLUTION", "SUMMARY", "SCHEDULE"):
        assert lines.count(section) == 1, section
    assert lines.index("GRID") < lines.index("PROPS") < lines.index("SCHEDULE")
    start = lines.index("COMPDAT") + 1
    records = [ln for ln in lines[start:] if ln.strip() and not ln.startswith("--")]
    end = records.index("/")
    conns = records[:end]
    assert len(conns) == sum(len(w.layers) for w in syn.WELLS)
    for ln in conns:
        items = ln.split()
        assert items[0].startswith("'") and items[-1] == "/" and items[3] == items[4]
        assert float(items[10]) == syn_deck.BASE_SKIN and items[7] == "1*"  # CF defaulted
    summary = "\n".join(lines[lines.index("SUMMARY"):lines.index("SCHEDULE")])
    for kw in ("WBHP", "WOPR", "WWPR", "WGPR", "WGOR", "WWCT"):
        assert f"\n{kw}\n " + " ".join(f"'{w.name}'" for w in syn.WELLS) in summary, kw


# ------------------------------------------------------------------------------ truth
def test_truth_has_information_in_every_response(truth: pd.DataFrame, case_dir: Path) -> None:
    steps = syn_deck.report_steps()
    assert sorted(set(truth.days)) == [s.days for s in steps]
    end = tomllib.loads((case_dir / syn.CASE_NAME).read_text())["case"]["history_end_days"]
    water, gas = [], []
    for w in syn.WELLS:
        wopr = _series(truth, w.name, "WOPR")
        hist = wopr.index <= end
        flowing = (wopr > 0).to_numpy()
        wct = _series(truth, w.name, "WWCT").to_numpy()
        gor = _series(truth, w.name, "WGOR").to_numpy()
        if wct[hist & flowing].max() > 0.05:
            water.append(w.name)
        g = gor[hist & flowing]
        if g.max() > 1.3 * g[0]:
            gas.append(w.name)
        # the oil rate is the control through the history (no well on its BHP floor)
        assert np.allclose(wopr.to_numpy()[hist & flowing], w.orat_sm3_day, rtol=1e-3), w.name
    assert len(water) >= 2, water
    assert len(gas) >= 2, gas

    # every yearly shut-in shows a pressure build-up in every well
    for w in syn.WELLS:
        bhp = _series(truth, w.name, "WBHP")
        wopr = _series(truth, w.name, "WOPR")
        for i, step in enumerate(steps):
            if not step.open_wells:
                assert wopr[step.days] == 0.0
                assert bhp[step.days] > bhp[steps[i - 1].days] + 5.0, (w.name, step.days)


def test_observed_noise_matches_sigma(observed: pd.DataFrame, truth: pd.DataFrame) -> None:
    assert list(observed.columns) == list(syn.OBSERVED_COLUMNS)
    assert set(observed.quantity) == {"WOPR", "WBHP", "WGOR", "WWCT"}
    units = observed.groupby("quantity")["units"].unique().map(list).to_dict()
    assert units == {"WOPR": ["sm3/day"], "WBHP": ["bar"], "WGOR": ["sm3/sm3"],
                     "WWCT": ["fraction"]}
    assert observed.date.iloc[0] == (syn_deck.START_DATE + pd.Timedelta(
        days=float(observed.days.iloc[0]))).isoformat()
    m = observed.merge(truth, on=["well", "days", "quantity"], suffixes=("", "_true"))
    assert len(m) == len(observed)

    oil = m[m.quantity == "WOPR"]
    assert oil.sigma.isna().all() and np.allclose(oil.value, oil.value_true, atol=1e-3)
    assert set(oil.flowing) == {0, 1}
    # GOR and WCT only while flowing; BHP flowing and shut-in with the documented sigmas
    assert (m[m.quantity.isin(["WGOR", "WWCT"])].flowing == 1).all()
    bhp = m[m.quantity == "WBHP"]
    assert set(bhp[bhp.flowing == 1].sigma) == {noise.BHP_SIGMA_FLOWING_BAR}
    assert set(bhp[bhp.flowing == 0].sigma) == {noise.BHP_SIGMA_SHUTIN_BAR}
    wct = m[m.quantity == "WWCT"]
    assert set(wct.sigma) == {noise.WCT_SIGMA_BEFORE, noise.WCT_SIGMA_AFTER}
    assert wct.value.between(0.0, 1.0).all()
    gor = m[m.quantity == "WGOR"]
    frac = (gor.sigma / gor.value_true).round(3)
    assert set(frac) == {noise.GOR_SIGMA_FRAC_BEFORE, noise.GOR_SIGMA_FRAC_AFTER}
    assert (gor.value >= 0).all()

    for q in ("WBHP", "WGOR", "WWCT"):
        sub = m[m.quantity == q]
        z = (sub.value - sub.value_true) / sub.sigma
        assert 0.5 < z.std() < 2.0, (q, z.std())
        assert abs(z.mean()) < 0.5, (q, z.mean())
    # correlated in time: lag-1 autocorrelation of BHP noise along each well's series
    lag1 = []
    for _, sub in bhp.sort_values("days").groupby("well"):
        z = ((sub.value - sub.value_true) / sub.sigma).to_numpy()
        lag1.append(np.corrcoef(z[:-1], z[1:])[0, 1])
    assert 0.4 < np.mean(lag1) < 0.9, lag1


def test_observed_loads_as_a_case(case_dir: Path) -> None:
    from hmcore.cases import load_case

    case = load_case(case_dir / syn.CASE_NAME)
    assert case.info.producers == [w.name for w in syn.WELLS]
    assert {"WWPR", "WGPR"} <= set(case.observed.quantity)  # derived from WOPR, WCT and GOR


@pytest.fixture(scope="module")
def rerun(case_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> SimulationResult:
    """The base deck run with the truth values applied by hmflow's deck editor."""
    from hmcore.model.run_deck import prepare_run_deck

    tmp = tmp_path_factory.mktemp("rerun")
    deck = prepare_run_deck(case_dir / syn.DECK_NAME, dict(syn.SYNTHETIC_TRUTH),
                            ParameterSpace.reference(), tmp / "deck")
    with SIMULATION_SLOTS:
        return OpmFlow().run(deck, tmp / "run")


def test_truth_is_reproduced_by_the_deck_editor(rerun: SimulationResult,
                                                truth: pd.DataFrame) -> None:
    again = syn.read_truth_responses(rerun.summary_path)
    key = ["well", "quantity", "days"]
    a = again.sort_values(key).reset_index(drop=True)
    b = truth.sort_values(key).reset_index(drop=True)
    assert a[["well", "quantity"]].equals(b[["well", "quantity"]])
    assert np.array_equal(a.days.to_numpy(float), b.days.to_numpy(float))
    assert np.array_equal(a.value.to_numpy(np.float32), b.value.to_numpy(np.float32))


def test_truth_space_with_hidden_parameter(rerun: SimulationResult, tmp_path: Path) -> None:
    """A truth space may hold extra effects; they reach the truth deck and truth.json."""
    hidden = Parameter(name="east_perm", kind="multiply", keywords=("PERMX", "PERMY"),
                       low=0.1, high=10.0, box=(15, 20, 1, 20, 1, 5))
    space = ParameterSpace(parameters=ParameterSpace.reference().parameters + (hidden,))
    seen: list[str] = []

    class ReplaySimulator:
        """Records the deck it is given and replays an earlier summary (no simulation)."""

        name = "replay"

        def run(self, deck: Path, run_dir: Path) -> SimulationResult:
            seen.append(deck.read_text())
            run_dir.mkdir(parents=True)
            smspec = rerun.summary_path
            for src in (smspec, smspec.with_suffix(".UNSMRY")):
                shutil.copy(src, run_dir / src.name)
            return SimulationResult(run_dir / smspec.name, run_dir, 0.0, self.name)

    with pytest.raises(KeyError, match="east_perm"):
        syn.write_synthetic_case(tmp_path / "x", 0, truth_space=space,
                                 simulator=ReplaySimulator())
    truth = {**syn.SYNTHETIC_TRUTH, "east_perm": 4.0}
    case = syn.write_synthetic_case(tmp_path / "hidden", 0, truth=truth, truth_space=space,
                                    simulator=ReplaySimulator(), history_end_days=1400)
    deck = seen[-1]
    assert "'PERMX' 4 15 20 1 20 1 5 /" in deck and "'PERMY' 0.6 /" in deck
    meta = json.loads((case.parent / syn.TRUTH_NAME).read_text())
    assert meta["parameters"]["east_perm"] == 4.0
    assert [p["name"] for p in meta["truth_space"]][-1] == "east_perm"
    assert tomllib.loads(case.read_text())["case"]["history_end_days"] == 1400
    with pytest.raises(ValueError, match="outside"):
        syn.write_synthetic_case(tmp_path / "y", 0, truth={"skin": 40.0},
                                 simulator=ReplaySimulator())
