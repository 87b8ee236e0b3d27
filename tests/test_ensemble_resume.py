"""`hmflow ensemble` killed with SIGKILL in the middle of an assimilation's member runs and
started again with the same command (here in the posterior's runs, after the update was
stored): it runs exactly the planned members, and none that was
journaled is simulated again (real OPM Flow behind a command template that logs every call,
real Prefect through the session's server, the CLI as a user types it; the small synthetic
case with two fields, conftest.small_case)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from collections import Counter

import pytest
from conftest import cli_env
from test_ensemble_flow import field_case

from storage import ArtifactStore, EvaluationJournal
from storage.ensemble import FORECAST_STEP, member_journal

pytestmark = [pytest.mark.opm]
# the prior, the posterior (one assimilation); 4 members (was 6, issue 40: suite time): the
# kill after 2 of the posterior's are journaled leaves 2 to run
SIZE, ROUNDS = 4, 2


@pytest.mark.timeout(600)
def test_a_killed_ensemble_resumes_with_exactly_the_planned_members(tmp_path, small_case,
                                                                    prefect_api):
    case, log = field_case(tmp_path / "case", small_case, "none",
                           f"size = {SIZE}\nweights = [1.0]\n")
    store = tmp_path / "store"
    args = [sys.executable, "-m", "hmflow.cli", "ensemble", "--case", str(case), "--campaign",
            "k", "--storage", str(store), "--workers", "2"]
    journals = [store / "k" / f"evaluations-{member_journal(i)}" for i in range(ROUNDS)]

    def journaled() -> dict[tuple[int, int], bytes]:
        return {(i, int(p.stem)): p.read_bytes() for i, folder in enumerate(journals)
                if folder.is_dir() for p in folder.glob("*.json") if p.stem.isdigit()}

    out = tmp_path / "killed.log"
    env = cli_env(prefect_api)
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=out.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True, env=env)
    deadline = time.time() + 300
    while (time.time() < deadline and proc.poll() is None
           and sum(1 for i, _ in journaled() if i == 1) < 2):
        time.sleep(0.1)
    os.killpg(proc.pid, signal.SIGKILL)  # mid-way through the posterior's member runs
    proc.wait(timeout=30)
    before = journaled()
    in_first = sum(1 for i, _ in before if i == 1)
    assert 2 <= in_first < SIZE and sum(1 for i, _ in before if i == 0) == SIZE, \
        out.read_text()[-3000:]
    calls_before = Counter(name.split(".")[0] for name in log.read_text().split())

    again = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=400,
                           env=env, check=False)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    after = journaled()
    assert sorted(after) == [(i, m) for i in range(ROUNDS) for m in range(SIZE)]
    assert all(after[key] == record for key, record in before.items())  # none journaled again
    # a run started again gets a fresh folder: i01-m0003.2 (tasks.simulate.fresh_dir)
    calls = Counter(name.split(".")[0] for name in log.read_text().split())
    for i, m in before:  # a journaled member's run is never started again
        assert calls[f"i{i:02d}-m{m:04d}"] == calls_before[f"i{i:02d}-m{m:04d}"] == 1
    # every other member ran once, but for at most one run per worker killed mid-way
    again_run = {name: n for name, n in calls.items() if (int(name[1:3]), int(name[-4:]))
                 not in before}
    assert len(again_run) == SIZE * ROUNDS - len(before)
    assert sum(n - 1 for n in again_run.values()) <= 2 and set(again_run.values()) <= {1, 2}
    records = EvaluationJournal(ArtifactStore(store), "k", member_journal(1)).rows()
    assert all(r["status"] != "FAIL" for r in records)
    assert ArtifactStore(store).latest("k", FORECAST_STEP) is not None
    said = " ".join(again.stdout.split())
    assert f"ensemble k: {SIZE} members, 1 assimilation(s), {SIZE * ROUNDS} runs (0 failed)" in said
    # the command's last words: the spread each field kept (issue 41: does it collapse?)
    for field in ("poro", "permx"):
        assert re.search(rf"field {field}: the posterior keeps \d+% of the prior's spread",
                         said), said
