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
    out = subprocess.run(["ps", "-eo", "pid=,pgid=,args="], capture_output=True, text=True).stdout
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
    rows = [json.loads(p.read_text()) for p in sorted(journal.glob("*.json"))]
    assert [r["index"] for r in rows] == list(range(len(done) + 2))
