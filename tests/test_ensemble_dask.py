"""An ensemble run on a Dask cluster: `hmflow ensemble --task-runner dask --dask-address ...`
with a `dask scheduler` and two `dask worker` processes started from the command line (real OPM
Flow, real Prefect, real store; tests/test_cluster.py's cluster). Every member's run happens in
a worker process, once, and the run ends with its forecast and report as on threads. The field
version of the small synthetic case (tests/test_ensemble_flow.py's ``field_case``), 2 members
(4 until 2026-11-28: CI's suite time, issue 40; two members on two workers still show where each
run happens), one assimilation, and the session's Prefect server (conftest.prefect_api)."""

from __future__ import annotations

import re
import subprocess
import sys
from collections import Counter

import pytest
from conftest import cli_env
from test_cluster import DASK, _worker_pids, dask_cluster
from test_ensemble_flow import field_case

from storage import ArtifactStore, EvaluationJournal
from storage.ensemble import FORECAST_STEP, REPORT_STEP, member_journal

pytestmark = [pytest.mark.opm,
              pytest.mark.skipif(not DASK.exists(), reason="the dask command is not installed")]
SIZE = 2


def test_every_member_runs_once_in_a_dask_worker(tmp_path, small_case, prefect_api):
    case, log = field_case(tmp_path / "case", small_case, "never-fails",
                           f"size = {SIZE}\nweights = [1.0]\nmin_realizations = 2\n")
    store_dir = tmp_path / "store"
    with dask_cluster(tmp_path) as cluster:
        pids = set(_worker_pids(cluster["address"]).values())
        done = subprocess.run(
            [sys.executable, "-m", "hmflow.cli", "ensemble", "--case", str(case), "--campaign",
             "dask", "--storage", str(store_dir), "--workers", "2", "--task-runner", "dask",
             "--dask-address", cluster["address"]],
            cwd=tmp_path, env=cli_env(prefect_api), capture_output=True, text=True,
            timeout=600, check=False)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-3000:]
    store = ArtifactStore(store_dir)
    records = [r for i in (0, 1) for r in EvaluationJournal(store, "dask", member_journal(i)).rows()]
    assert sorted((r["phase"], r["index"]) for r in records) == [
        (f"i{i:02d}", m) for i in (0, 1) for m in range(SIZE)]
    assert all(r["status"] != "FAIL" for r in records)
    assert {r["host_pid"] for r in records} <= pids  # run by the workers, not the flow's process
    # one simulator call per member run: the logging wrapper saw each run folder once
    calls = Counter(log.read_text().split())
    assert sorted(calls) == sorted(f"i{i:02d}-m{m:04d}" for i in (0, 1) for m in range(SIZE))
    assert set(calls.values()) == {1}
    assert store.latest("dask", FORECAST_STEP) is not None
    assert store.latest("dask", REPORT_STEP) is not None
    # the command's last words: the spread each field kept (issue 41: does it collapse?)
    assert re.search(r"field poro: the posterior keeps \d+% of the prior's spread", out), out
    assert re.search(r"field permx: the posterior keeps \d+% of the prior's spread", out), out
