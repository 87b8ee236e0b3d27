"""Campaigns whose simulator calls run as Slurm jobs (issue 43): a real one-node Slurm
(tests/slurm_cluster.py: munged, slurmctld, slurmd on this host), `hmflow run --cluster slurm`
on the small synthetic case with a ``[cluster]`` section (real OPM Flow, real Prefect, the
session's server). Each call's record names the Slurm job that ran it and ``sacct`` lists
those jobs; a job cancelled with ``scancel`` in the middle of a call has that call run again
in another job, and the journal ends with exactly the budget. A ``[cluster]`` whose walltime
cannot hold a call is refused before anything is submitted."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import cli_env
from slurm_cluster import one_node_slurm, skip_reason

pytestmark = [pytest.mark.opm,
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]

CLUSTER = """
[cluster]
queue = "debug"
cores = 1
memory = "1GB"
walltime = "00:30:00"
max_jobs = 2
"""


@pytest.fixture(scope="module")
def slurm():
    with one_node_slurm() as running:
        yield running


def _case(small_case: Path, root: Path, section: str = CLUSTER) -> Path:
    folder = root / "case"
    shutil.copytree(small_case.parent, folder)
    case = folder / "case.toml"
    case.write_text(case.read_text() + section)
    return case


def _run(slurm, case: Path, root: Path, campaign: str, budget: int, api: str
         ) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "hmflow.cli", "run", "--case", str(case), "--agent", "random",
         "--budget", str(budget), "--workers", "2", "--seed", "4", "--campaign", campaign,
         "--storage", str(root / "store"), "--cluster", "slurm"],
        cwd=root, env=cli_env(api, SLURM_CONF=slurm.env["SLURM_CONF"], COLUMNS="200"),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


def _records(root: Path, campaign: str) -> list[dict]:
    return [json.loads(p.read_text())
            for p in sorted((root / "store" / campaign / "evaluations").glob("*.json"))]


def _job_of_simulation(run_dirs: list[Path]) -> tuple[str, Path] | None:
    """(Slurm job id, run dir) of a simulator process running in one of ``run_dirs``: the
    simulator's command line names its run directory, its environment its job."""
    wanted = {str(d): d for d in run_dirs}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            env = (proc / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        hit = next((d for s, d in wanted.items() if s in cmd), None)
        job = next((v.split(b"=", 1)[1].decode() for v in env
                    if v.startswith(b"SLURM_JOB_ID=")), None)
        if hit is not None and job:
            return job, hit
    return None


def test_a_campaign_runs_its_calls_in_slurm_jobs_and_a_cancelled_job_is_rerun(
        slurm, small_case, prefect_api, tmp_path):
    """One campaign shows both (the jobs' start is the cost): every call ran in a Slurm job
    that sacct lists, and a job cancelled mid-call loses and duplicates nothing."""
    budget = 4
    case = _case(small_case, tmp_path)
    run = _run(slurm, case, tmp_path, "queued", budget, prefect_api)
    runs = tmp_path / "store" / "queued" / "runs"
    cancelled, deadline = None, time.monotonic() + 600
    while cancelled is None and run.poll() is None and time.monotonic() < deadline:
        started = [p for p in runs.iterdir()] if runs.is_dir() else []
        done = {r["index"] for r in _records(tmp_path, "queued")}
        # a call of the campaign (not the reference run) still running, after the first
        running = [p for p in started if re.fullmatch(r"00000[1-3]", p.name)
                   and int(p.name) not in done]
        found = _job_of_simulation(running)
        if found is not None:
            cancelled = found
            slurm.run("scancel", cancelled[0])
        time.sleep(0.2)
    out, _ = run.communicate(timeout=900)
    assert cancelled is not None, out[-4000:]
    assert run.returncode == 0, out[-4000:]
    rows = _records(tmp_path, "queued")
    assert [r["index"] for r in rows] == list(range(budget))
    assert all(r["status"] in ("COMPLETE", "INVALID") for r in rows), rows
    jobs = slurm.finished_jobs()
    ran_in = {r["batch_job"] for r in rows}
    # every call ran in a Slurm job of hmflow's that sacct lists
    assert ran_in <= set(jobs), (ran_in, jobs)
    assert all(jobs[j]["name"] == "hmflow" for j in ran_in), jobs
    assert jobs[cancelled[0]]["state"].startswith("CANCELLED"), jobs[cancelled[0]]
    # the cancelled call ran again, in another job and a fresh run directory beside the one
    # it left (the cancelled job may have run earlier calls)
    index = int(cancelled[1].name)
    assert rows[index]["batch_job"] != cancelled[0], rows[index]
    assert Path(rows[index]["run_dir"]).name == f"{cancelled[1].name}.2", rows[index]
    assert cancelled[0] in jobs and len(jobs) >= 2  # the cancelled job and the one rerunning


def test_a_walltime_shorter_than_a_call_is_refused_before_any_job(slurm, small_case,
                                                                  prefect_api, tmp_path):
    case = _case(small_case, tmp_path, CLUSTER.replace('"00:30:00"', '"00:05:00"'))
    before = set(slurm.finished_jobs())
    run = _run(slurm, case, tmp_path, "short", 1, prefect_api)
    out, _ = run.communicate(timeout=300)
    assert run.returncode == 2, out
    assert "cluster.walltime" in out and "timeout_s 900 s" in out, out
    assert set(slurm.finished_jobs()) == before and not slurm.running_jobs()
    assert not (tmp_path / "store" / "short").exists()
