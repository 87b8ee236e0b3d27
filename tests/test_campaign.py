"""Campaign flow end to end with real OPM runs, real Prefect (ephemeral server) and real files."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pandas as pd
import pytest

from hmcore.alignment import align
from hmcore.case import load_case
from hmcore.evaluation import score_responses
from hmcore.responses import read_responses
from hmcore.simulator import OpmFlow
from storage import ArtifactStore, EvaluationJournal

PUNQ = Path(__file__).resolve().parents[2] / "shared" / "punqs3"
FIXTURES = Path(__file__).parent / "fixtures"
pytestmark = [pytest.mark.opm,
              pytest.mark.skipif(not PUNQ.is_dir(), reason=f"PUNQ-S3 data not found at {PUNQ}")]


def write_case(tmp_path: Path, extra: str = "") -> Path:
    path = tmp_path / "punq.toml"
    path.write_text(f"""[case]
name = "punq"
deck = "{PUNQ / 'PUNQS3.DATA'}"
observed = "{PUNQ / 'punqs3_observed_full_history.csv'}"
history_end_days = 2200
{extra}""")
    return path


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """A 6-call campaign whose simulator fails (a real non-zero exit) when PERMX x > 1.5."""
    from flows.campaign import campaign_flow

    tmp = tmp_path_factory.mktemp("campaign")
    template = f"bash {FIXTURES / 'failing_simulator.sh'} {{deck}} {{run_dir}} {sys.executable}"
    case = write_case(tmp, f'\n[simulator]\nbackend = "{template}"\ntimeout_s = 300\n')
    storage = tmp / "store"
    result = campaign_flow(case=str(case), agent="random", budget=6, workers=2, seed=5,
                           storage=str(storage), campaign="punq-test")
    return {"case": case, "storage": storage, "result": result, "name": "punq-test"}


def test_parquet_has_one_row_per_call_including_failures(campaign):
    store = ArtifactStore(campaign["storage"])
    table = store.latest(campaign["name"], "results").read_parquet("evaluations.parquet")
    assert list(table["index"]) == list(range(6))
    failed = table[table["p_permx_mult"] > 1.5]
    assert len(failed) >= 1, "seed 5 should propose PERMX x > 1.5 at least once"
    assert (failed["status"] == "FAIL").all()
    assert failed["reason"].str.contains("crash").all() and failed["E"].isna().all()
    ok = table[table["p_permx_mult"] <= 1.5]
    assert (ok["status"] == "COMPLETE").all() and ok["E"].gt(0).all()
    for col in ("p_poro_mult", "a_skin", "penalty", "reward", "loss_bhp", "coverage", "wall_time_s",
                "run_dir", "seed", "E_heldout"):
        assert col in table.columns
    assert (failed["reward"] < ok["reward"].min()).all()  # failures are penalised
    best = store.latest(campaign["name"], "best").read_json("metrics.json")
    assert best["status"] == "COMPLETE" and best["E"] == pytest.approx(ok["E"].min())


def test_archived_best_case_resimulates_to_the_same_metrics(campaign, tmp_path):
    store = ArtifactStore(campaign["storage"])
    best = store.latest(campaign["name"], "best")
    stored = best.read_json("metrics.json")
    deck = best.file("PUNQS3.DATA")
    result = OpmFlow().run(deck, tmp_path / "rerun")
    case = load_case(campaign["case"])
    s = score_responses(case, read_responses(result.summary_path, sorted(case.info.wells)))
    assert s["E"] == pytest.approx(stored["E"], rel=1e-9)
    assert s["metrics"]["macro"]["cmatch"] == pytest.approx(stored["metrics"]["macro"]["cmatch"],
                                                             rel=1e-9)
    # and the archived summary itself scores the same
    archived = read_responses(best.file("PUNQS3.SMSPEC"), sorted(case.info.wells))
    assert score_responses(case, archived)["E"] == pytest.approx(stored["E"], rel=1e-12)


def test_report_only_rerun_makes_zero_simulator_calls(campaign, monkeypatch):
    from flows.report import report_flow
    import hmcore.simulator as simulator

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

    with pytest.raises(ValueError, match="other settings"):
        campaign_flow(case=str(campaign["case"]), agent="random", budget=2, workers=2, seed=6,
                      storage=str(campaign["storage"]), campaign=campaign["name"])
