"""`hmflow diagnose` killed with SIGKILL mid-run and started again with the same command
replays the runs it had journaled and simulates only the others (real OPM Flow, real Prefect,
the CLI as a user types it; the small synthetic case, conftest.small_case, and the session's
Prefect server: what is tested is the journal, not the case or the server)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from conftest import cli_env

BUDGET = 8
"""The minimum of one family searched from a given calibrated point: 1 run of it, then one
batch of 2 aquifer probes and 5 finite differences."""
RUN_DIR = re.compile(r".+-(?P<n>\d+)(\.\d+)?")


def test_a_journaled_run_is_replayed_and_one_of_other_values_refused(tmp_path):
    """The replay without a simulator: a journaled run comes back with its responses table,
    the same to the last bit; a run journaled with other values stops the diagnosis."""
    from storage import ArtifactStore, EvaluationJournal
    from tasks.diagnose import JournaledRuns
    from tasks.simulate import responses_record

    class NoRunner:
        def submit(self, *args):
            raise AssertionError("a journaled run was submitted")

    frame = pd.DataFrame({"well": ["P1"], "days": [1.5], "quantity": ["WBHP"], "value": [0.1]})
    EvaluationJournal(ArtifactStore(tmp_path), "d", "diagnosis-x").record(0, {
        "params": {"a": 1.0}, "status": "COMPLETE", "E": 0.5, "responses": responses_record(frame)})
    [ev] = JournaledRuns(str(tmp_path), "d", "diagnosis-x", NoRunner())(None, [{"a": 1.0}], "c")
    assert ev.E == 0.5 and ev.responses.equals(frame)
    with pytest.raises(RuntimeError, match="diverged at run 0"):
        JournaledRuns(str(tmp_path), "d", "diagnosis-x", NoRunner())(None, [{"a": 1.1}], "c")


@pytest.mark.opm
def test_a_killed_diagnosis_resumes_without_simulating_a_journaled_run_again(tmp_path,
                                                                             small_case,
                                                                             prefect_api):
    from hmcore.cases import load_case
    from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH
    from storage import ArtifactStore
    from tasks.case import prepare_deck

    shutil.copytree(small_case.parent, tmp_path / "syn")
    store = tmp_path / "store"
    case = load_case(tmp_path / "syn" / "case.toml")
    prepare_deck.fn(case, "syn/case.toml", str(store), "b")  # a campaign's best, as archived
    best = {n: float(SYNTHETIC_TRUTH.get(n, 1.0)) for n in case.space.names}
    ArtifactStore(store).put_files("b", "best", {"index": 0}, {"params.json": best}, "test")
    args = [sys.executable, "-m", "hmflow.cli", "diagnose", "--from-campaign", "b", "--storage",
            str(store), "--kinds", "aquifer_strength", "--budget", str(BUDGET), "--workers", "2"]
    runs = store / "b" / "diagnosis-runs"

    def journaled() -> dict[int, bytes]:
        return {int(p.stem): p.read_bytes()
                for p in (store / "b").glob("evaluations-diagnosis-*/*.json") if p.stem.isdigit()}

    log = tmp_path / "killed.log"
    env = cli_env(prefect_api)
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True, env=env)
    deadline = time.time() + 300
    while time.time() < deadline and len(journaled()) < 3 and proc.poll() is None:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    before = journaled()
    assert 3 <= len(before) < BUDGET, log.read_text()[-3000:]
    made = set(os.listdir(runs))

    again = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=600,
                           env=env)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    after = journaled()
    assert all(after[i] == record for i, record in before.items())  # nothing journaled again
    simulated = {int(RUN_DIR.fullmatch(name)["n"]) for name in set(os.listdir(runs)) - made}
    assert simulated and not simulated & set(before), (sorted(simulated), sorted(before))
    doc = json.loads(sorted((store / "b" / "diagnosis-report").glob("v*/diagnosis.json"))[-1]
                     .read_text())
    assert doc["cost"]["simulations"] == len(after) == BUDGET
    assert sorted(after) == list(range(BUDGET))
