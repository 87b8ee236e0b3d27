"""Campaign flow end to end with real OPM runs, real Prefect (ephemeral server) and real files,
on the small synthetic case (conftest.small_case: what is tested is the campaign, not the
case; PUNQ-S3's own runs are tested in test_punqs3 and test_simulator)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import cli_env

from hmcore.calibration.calls import POINT_ATOL
from hmcore.calibration.methods.lm import FD_STEP, jacobian_base
from hmcore.calibration.registry import DEFAULT_AGENT
from hmcore.scoring.alignment import align
from hmcore.cases import load_case
from hmcore.scoring.evaluation import score_responses
from hmcore.simulation.responses import read_responses
from hmcore.simulation.simulator import OpmFlow
from storage import ArtifactStore, EvaluationJournal

FIXTURES = Path(__file__).parent / "fixtures"
pytestmark = [pytest.mark.opm]


def write_case(tmp_path: Path, small_case: Path, extra: str = "") -> Path:
    """A copy of the small synthetic case in ``tmp_path`` with ``extra`` added to its TOML.

    Measured as a field's history is: its truth is left out (unknown), and GOR and water cut
    are recorded as 0 at the shut-ins, as PUNQ-S3's measured data records them (the synthetic
    history has no ratio where nothing flows), so the shut-in records are there to be left
    out of the ratios' metrics and counted."""
    shutil.copytree(small_case.parent, tmp_path / "case",
                    ignore=shutil.ignore_patterns("truth*"))
    path = tmp_path / "case" / small_case.name
    path.write_text(path.read_text() + extra)
    observed = tmp_path / "case" / "observed.csv"
    obs = pd.read_csv(observed)
    shut = obs[(obs.quantity == "WOPR") & (obs.value == 0.0)]
    ratios = [shut.assign(quantity=q, units=u, value=0.0, sigma=float("nan"))
              for q, u in (("WGOR", "sm3/sm3"), ("WWCT", "fraction"))]
    pd.concat([obs, *ratios], ignore_index=True).sort_values(
        ["well", "days"], kind="stable").to_csv(observed, index=False)
    return path


@pytest.fixture(scope="module")
def campaign(tmp_path_factory, small_case):
    """A 6-call campaign whose simulator fails (a real non-zero exit) when PERMX x > 1.5."""
    from flows.campaign import campaign_flow

    tmp = tmp_path_factory.mktemp("campaign")
    template = f"bash {FIXTURES / 'failing_simulator.sh'} {{deck}} {{run_dir}} {sys.executable}"
    case = write_case(tmp, small_case,
                      f'\n[simulator]\nbackend = "{template}"\ntimeout_s = 300\n')
    storage = tmp / "store"
    result = campaign_flow(case=str(case), agent="random", budget=6, workers=2, seed=5,
                           storage=str(storage), campaign="c-test")
    return {"case": case, "storage": storage, "result": result, "name": "c-test"}


def test_parquet_has_one_row_per_call_including_failures(campaign):
    store = ArtifactStore(campaign["storage"])
    table = store.latest(campaign["name"], "results").read_parquet("evaluations.parquet")
    assert list(table["index"]) == list(range(6))
    failed = table[table["p_permx_mult"] > 1.5]
    assert len(failed) >= 1, "seed 5 should propose PERMX x > 1.5 at least once"
    assert (failed["status"] == "FAIL").all()
    assert failed["reason"].str.contains("crash").all() and failed["E"].isna().all()
    ok = table[table["p_permx_mult"] <= 1.5]
    # scored: valid, or simulated and penalised by a physics check (never best)
    assert ok["status"].isin(["COMPLETE", "INVALID"]).all() and ok["E"].gt(0).all()
    assert (ok.loc[ok.status == "INVALID", "penalty"] > 0).all()
    assert (ok.loc[ok.status == "COMPLETE", "penalty"] == 0).all()
    valid = ok[ok.status == "COMPLETE"]
    assert len(valid) >= 1
    for col in ("p_poro_mult", "a_skin", "penalty", "reward", "loss_bhp", "coverage", "wall_time_s",
                "run_dir", "seed", "E_heldout"):
        assert col in table.columns
    assert (failed["reward"] < ok["reward"].min()).all()  # failures are penalised
    best = store.latest(campaign["name"], "best").read_json("metrics.json")
    key = best["objective"]  # the case's objective chooses: the likelihood by default
    assert key == "likelihood" and valid[key].notna().all()
    assert best["status"] == "COMPLETE" and best[key] == pytest.approx(valid[key].min())


def test_archived_best_case_resimulates_to_the_same_metrics(campaign, tmp_path):
    store = ArtifactStore(campaign["storage"])
    best = store.latest(campaign["name"], "best")
    stored = best.read_json("metrics.json")
    deck = best.file("SYNTH.DATA")
    result = OpmFlow().run(deck, tmp_path / "rerun")
    case = load_case(campaign["case"])
    s = score_responses(case, read_responses(result.summary_path, sorted(case.info.wells)))
    assert s["E"] == pytest.approx(stored["E"], rel=1e-9)
    assert s["metrics"]["macro"]["cmatch"] == pytest.approx(stored["metrics"]["macro"]["cmatch"],
                                                             rel=1e-9)
    # and the archived summary itself scores the same
    archived = read_responses(best.file("SYNTH.SMSPEC"), sorted(case.info.wells))
    assert score_responses(case, archived)["E"] == pytest.approx(stored["E"], rel=1e-12)


def test_report_only_rerun_makes_zero_simulator_calls(campaign, monkeypatch):
    from flows.report import report_flow
    import hmcore.simulation.simulator as simulator

    def forbidden(*args, **kwargs):
        raise AssertionError("the report stage must not run the simulator")

    monkeypatch.setattr(simulator.OpmFlow, "run", forbidden)
    monkeypatch.setattr(simulator.CommandLineSimulator, "run", forbidden)
    runs_before = sorted(p.name for p in (campaign["storage"] / campaign["name"] / "runs").iterdir())
    out = report_flow(storage=str(campaign["storage"]), campaign=campaign["name"])
    runs_after = sorted(p.name for p in (campaign["storage"] / campaign["name"] / "runs").iterdir())
    assert runs_before == runs_after
    text = Path(out["report_path"]).read_text()
    assert "C_match" in text and "Best case" in text
    doc = json.loads(Path(out["report_path"]).with_name("report.json").read_text())
    assert doc["calls"] == 6 and doc["best"]["E"] > 0


def test_rerun_resumes_and_extends_without_resimulating(campaign):
    from flows.campaign import campaign_flow

    store = ArtifactStore(campaign["storage"])
    journal = EvaluationJournal(store, campaign["name"])
    before = {r["index"]: r for r in journal.rows()}
    runs = campaign["storage"] / campaign["name"] / "runs"
    n_runs = len(list(runs.iterdir()))
    campaign_flow(case=str(campaign["case"]), agent="random", budget=8, workers=2, seed=5,
                  storage=str(campaign["storage"]), campaign=campaign["name"])
    after = {r["index"]: r for r in journal.rows()}
    assert sorted(after) == list(range(8))
    assert all(after[i] == before[i] for i in before)  # nothing redone or overwritten
    assert len(list(runs.iterdir())) == n_runs + 2     # only the two new calls ran
    assert store.latest(campaign["name"], "results").version >= 2


def test_same_name_with_other_settings_is_refused(campaign):
    from flows.campaign import campaign_flow

    state = campaign_flow(case=str(campaign["case"]), agent="random", budget=2, workers=2,
                          seed=6, storage=str(campaign["storage"]), campaign=campaign["name"],
                          return_state=True)
    assert state.is_failed() and "other settings {'seed': (5, 6)}" in state.message


def test_tables_command_prints_the_papers_three_tables_from_storage(campaign, tmp_path,
                                                                    monkeypatch):
    """`hmflow tables` rescores the stored best run with the paper's formulas, no simulator."""
    from typer.testing import CliRunner

    import hmcore.simulation.simulator as simulator
    from hmflow.cli import app

    def forbidden(*args, **kwargs):
        raise AssertionError("tables must not run the simulator")

    monkeypatch.setattr(simulator.OpmFlow, "run", forbidden)
    monkeypatch.setattr(simulator.CommandLineSimulator, "run", forbidden)
    md = tmp_path / "tables.md"
    args = ["tables", "--storage", str(campaign["storage"]), "--campaign", campaign["name"]]
    result = CliRunner().invoke(app, args + ["--markdown", str(md)], env={"COLUMNS": "220"})
    assert result.exit_code == 0, result.output
    for title in ("match by category", "C_match (%) per well and category",
                  "GOR and water cut per well"):
        assert title in result.output
    text = md.read_text()
    # the shut-in records are left out of GOR and WCT and counted, per well and in all
    assert "shut_in_observed" in text and "| gor | all |" in text
    best = ArtifactStore(campaign["storage"]).latest(campaign["name"], "best")
    stored = best.read_json("metrics.json")["metrics"]
    macro = next(line for line in text.splitlines() if line.startswith("| macro"))
    assert f"| {stored['macro']['nmse']:.4f} |" in macro and \
        f"| {100 / (1 + stored['macro']['nmse']):.2f} |" in macro
    # one call by number (from 1); a failed call has no summary to score; a call that does
    # not exist is refused with the count
    rows = EvaluationJournal(ArtifactStore(campaign["storage"]), campaign["name"]).rows()
    ok = next(r["index"] + 1 for r in rows if r["status"] != "FAIL")
    assert CliRunner().invoke(app, args + ["--call", str(ok)]).exit_code == 0
    failed = next(r["index"] + 1 for r in rows if r["status"] == "FAIL")
    no_summary = CliRunner().invoke(app, args + ["--call", str(failed)])
    assert no_summary.exit_code == 2 and "no summary file" in " ".join(no_summary.output.split())
    missing = CliRunner().invoke(app, args + ["--call", "99"])
    assert missing.exit_code == 2 and "has no call 99" in missing.output
    again = CliRunner().invoke(app, args + ["--markdown", str(md)])
    assert again.exit_code == 2 and "never overwrites" in again.output


def test_sac_paper_campaign_journals_and_resumes_with_the_real_simulator(tmp_path, small_case):
    """`sac-paper` through the campaign flow: 2 real OPM calls, 2 at a time, then resumed to 4
    (only 2 new runs, on both lanes; the first 2 records untouched)."""
    from flows.campaign import campaign_flow

    case, storage = write_case(tmp_path, small_case), tmp_path / "store"
    kw = dict(case=str(case), agent="sac-paper", workers=2, seed=3, storage=str(storage),
              campaign="paper")
    campaign_flow(budget=2, **kw)
    journal = EvaluationJournal(ArtifactStore(storage), "paper")
    before = {r["index"]: r for r in journal.rows()}
    assert sorted(before) == [0, 1]
    assert all(r["agent"] == "sac-paper" and r["status"] in ("COMPLETE", "INVALID")
               for r in before.values())
    assert [r["lane"] for r in before.values()] == [0, 1]
    campaign_flow(budget=4, **kw)
    after = {r["index"]: r for r in journal.rows()}
    assert sorted(after) == list(range(4)) and all(after[i] == before[i] for i in before)
    assert all(after[i]["agent"] == "sac-paper" and after[i]["status"] in ("COMPLETE", "INVALID")
               for i in (2, 3))
    assert [after[i]["lane"] for i in (2, 3)] == [0, 1]
    assert len(list((storage / "paper" / "runs").iterdir())) == 4


def test_a_call_journaled_before_its_worker_died_is_not_simulated_again(tmp_path):
    """A cluster reruns the task of a worker that died after journaling its record: the rerun
    returns the journaled record and neither simulates nor records again."""
    from hmcore.calibration.calls import Job
    from storage import ArtifactStore, EvaluationJournal
    from tasks.simulate import simulate

    journal = EvaluationJournal(ArtifactStore(tmp_path), "c")
    journal.record(2, {"E": 0.25, "status": "COMPLETE", "action": [0.0]})
    job = Job(2, {"x": 1.0}, (0.0,), 0, "explore")
    got = simulate.fn(None, job, str(tmp_path), "c", 0, "random")  # no case: nothing may run
    assert got == journal.get(2) and not (tmp_path / "c" / "runs").exists()


def test_the_default_campaign_simulates_no_point_twice_and_keeps_its_jacobian_valid(
        tmp_path, small_case, prefect_api):
    """`hmflow run` as `make run` types it (the default method, lm; 2 workers; seed 0) on the
    small synthetic case, 16 calls: no two calls of the journal are of the same point, and no
    Jacobian run breaks a physics check its base passes (its finite-difference step went the
    other way). The descents meet the porosity-permeability trend check there: lm version 2
    sent a Jacobian run across it at call 44 (and 11 more by call 100); version 4's steps
    turned at calls 9, 10, 27 and 28 of 50, version 6's (one Jacobian column anew per
    accepted step) at calls 27, 31 and 32 of 40 (their journals, 0-based): 32 calls here."""
    assert DEFAULT_AGENT == "lm"
    budget = 32
    run = subprocess.run([sys.executable, "-m", "hmflow.cli", "run", "--case", str(small_case),
                          "--budget", str(budget), "--storage", str(tmp_path / "store")],
                         cwd=tmp_path, env=cli_env(prefect_api, COLUMNS="150"),
                         capture_output=True, text=True, timeout=1200, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
    (campaign,) = [p.name for p in (tmp_path / "store").iterdir()
                   if p.name.startswith("synthetic-small-lm")
                   and not p.name.endswith("-reference")]
    rows = EvaluationJournal(ArtifactStore(tmp_path / "store"), campaign).rows()
    assert [r["index"] for r in rows] == list(range(budget))
    space = load_case(small_case).space
    u = np.array([space.to_action(r["params"]) for r in rows])
    twice = [(i, j) for i in range(len(u)) for j in range(i)
             if np.max(np.abs(u[i] - u[j])) <= POINT_ATOL]
    assert not twice
    broken = []
    for r in rows:
        if r["phase"] != "jacobian":
            continue
        base = jacobian_base(r, rows)
        assert base is not None, f"call {r['index']}: no base one step away"
        if set(r.get("violation_kinds") or ()) - set(base.get("violation_kinds") or ()):
            broken.append((r["index"], base["index"], r["violation_kinds"]))
    assert not broken
    # the edge was met: some finite-difference step went downwards where upwards stays in
    # the box (it would have broken a check)
    turned = []
    for r in rows:
        if r["phase"] == "jacobian":
            step = np.asarray(r["action"]) - np.asarray(jacobian_base(r, rows)["action"])
            k = int(np.argmax(np.abs(step)))
            if step[k] < 0 and jacobian_base(r, rows)["action"][k] + FD_STEP <= 1.0:
                turned.append(r["index"])
    assert turned, "no finite-difference step turned: the campaign never met a check"
