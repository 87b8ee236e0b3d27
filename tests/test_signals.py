"""SIGTERM (``kill PID``, a batch system's time limit) stops `hmflow run` as Ctrl-C does: it
exits, the temporary Prefect server it started is gone with it, and the same command resumes
the campaign from its journal (real OPM Flow, real Prefect)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest


def _alive(pgid: int) -> list[str]:
    out = subprocess.run(["ps", "-eww", "-o", "pid=,pgid=,args="], capture_output=True,
                         text=True).stdout
    return [line for line in out.splitlines() if int(line.split()[1]) == pgid]


@pytest.mark.opm
def test_sigterm_stops_the_campaign_and_its_temporary_server(tmp_path):
    store = tmp_path / "store"
    args = [sys.executable, "-m", "hmflow.cli", "run", "--agent", "random", "--budget", "40",
            "--workers", "2", "--campaign", "term", "--storage", str(store)]
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    journal = store / "term" / "evaluations"
    deadline = time.time() + 300
    while time.time() < deadline and len(list(journal.glob("*.json"))) < 2:
        time.sleep(0.5)
    assert len(list(journal.glob("*.json"))) >= 2, proc.communicate(timeout=60)[0][-3000:]
    os.kill(proc.pid, signal.SIGTERM)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode != 0 and "Traceback" not in out, out[-3000:]
    time.sleep(3)
    assert not _alive(proc.pid), _alive(proc.pid)  # no server, no simulator left behind
    done = sorted(int(p.stem) for p in journal.glob("*.json"))
    assert done == list(range(len(done)))  # whole records only, from 0
    rerun = subprocess.run(args[:-4] + ["--budget", str(len(done) + 2), "--campaign", "term",
                                        "--storage", str(store)],
                           cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    assert f"resuming campaign term: {len(done)} calls already journaled" in rerun.stdout
    assert "Error logging to API" not in rerun.stdout + rerun.stderr  # logs sent before it stops
    rows = [json.loads(p.read_text()) for p in sorted(journal.glob("*.json"))]
    assert [r["index"] for r in rows] == list(range(len(done) + 2))


@pytest.mark.opm
def test_kill_9_of_hmflow_leaves_no_server_and_no_simulator(tmp_path):
    """SIGKILL cannot be caught: what hmflow started must die with it by itself (the
    temporary Prefect server and the simulators are killed by the kernel, PR_SET_PDEATHSIG),
    and the campaign resumes from its journal."""
    store = tmp_path / "store"
    args = [sys.executable, "-m", "hmflow.cli", "run", "--agent", "random", "--budget", "40",
            "--workers", "2", "--campaign", "k9", "--storage", str(store)]
    log = tmp_path / "hmflow.log"
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)
    journal = store / "k9" / "evaluations"
    deadline = time.time() + 300
    while time.time() < deadline and len(list(journal.glob("*.json"))) < 2:
        time.sleep(0.5)
    assert len(list(journal.glob("*.json"))) >= 2, log.read_text()[-3000:]
    before = _alive(proc.pid)
    assert any("prefect.server.api.server:create_app" in line for line in before), (
        before, log.read_text()[-3000:], os.environ.get("PREFECT_API_URL"))
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    deadline = time.time() + 20
    while time.time() < deadline and _alive(proc.pid):
        time.sleep(0.5)
    assert not _alive(proc.pid), _alive(proc.pid)
    done = len(list(journal.glob("*.json")))
    rerun = subprocess.run(args[:-6] + ["--budget", str(done + 1), "--campaign", "k9",
                                        "--storage", str(store)],
                           cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    assert sorted(int(p.stem) for p in journal.glob("*.json")) == list(range(done + 1))
