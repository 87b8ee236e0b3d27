"""The Prefect server's own services, for real: its scheduler creates the runs of a deployment
with an interval schedule and a `prefect worker start` process runs them; `prefect flow-run ls`
(the CLI) lists them.

Guards the pins in pyproject.toml: with SQLAlchemy 2.1 the scheduler's bulk insert fails on
every cycle ("Can't evaluate bulk DML statement"), so a scheduled deployment gets no runs; with
fastapi 0.151 and later (0.154 was installed) the server answers `prefect flow-run ls` with
422 Unprocessable Entity (it refuses the nulls the CLI sends).

The server is the session's (conftest.prefect_server: a `prefect server start` on SQLite with a
temporary PREFECT_HOME; its default scheduler settings are enough here: the
"recent deployments" scheduler visits a new deployment within 5 s). The deployed flow is a tiny
flow written under tmp_path, so no simulation runs. Server and worker are stopped in teardown.
"""

from __future__ import annotations

import subprocess
import time

import pytest

from prefect_processes import PREFECT, serve_worker, tail
from test_deployments import api_settings  # noqa: F401 (a fixture)

POOL = "hmflow-sched-test"
FLOW_NAME = "hmflow-sched-probe"
DEPLOYMENT = "every-10s"
INTERVAL_S = 10
WAIT_S = 180

pytestmark = pytest.mark.skipif(not PREFECT.is_file(), reason=f"prefect CLI not found at {PREFECT}")

PROBE_FLOW = f'''
from pathlib import Path

from prefect import flow
from prefect.runtime import flow_run


@flow(name="{FLOW_NAME}", log_prints=True)
def probe(out_dir: str) -> int:
    Path(out_dir, f"{{flow_run.id}}.done").write_text(flow_run.name)
    return 1
'''


@pytest.fixture(scope="module")
def scheduled_deployment(api_settings, tmp_path_factory):
    """A process work pool and a deployment of the probe flow on a 10 s interval schedule."""
    from prefect import Flow
    from prefect.schedules import Interval

    from deployments.campaign import ensure_work_pool

    src = tmp_path_factory.mktemp("probe-src")
    (src / "probe_flow.py").write_text(PROBE_FLOW)
    out = tmp_path_factory.mktemp("probe-out")
    ensure_work_pool(POOL)
    flow = Flow.from_source(source=str(src), entrypoint="probe_flow.py:probe")
    deployment = flow.to_deployment(name=DEPLOYMENT, work_pool_name=POOL,
                                    schedules=[Interval(INTERVAL_S)],
                                    parameters={"out_dir": str(out)})
    return {"id": deployment.apply(work_pool_name=POOL), "out": out}


@pytest.fixture(scope="module")
def worker(prefect_server, scheduled_deployment):
    with serve_worker(prefect_server, POOL, "sched-worker") as w:
        yield w


def _runs_of(deployment_id) -> list:
    """The deployment's flow runs, earliest expected start first. Sort and limit are given: the
    server with fastapi >= 0.151 refuses the nulls the client sends for them (422), and this
    test's outcome must depend on the scheduler only. (An empty task-run filter is not sent: it
    would keep only flow runs that have task runs.)"""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
    from prefect.client.schemas.sorting import FlowRunSort

    with get_client(sync_client=True) as client:
        return client.read_flow_runs(
            deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment_id])),
            sort=FlowRunSort.EXPECTED_START_TIME_ASC, limit=200, offset=0)


def _diagnostics(prefect_server, worker) -> str:
    server_log = prefect_server["log"].read_text(errors="replace").splitlines()
    errors = [ln for ln in server_log if "Error" in ln or "Exception" in ln][-15:]
    return ("server log error lines:\n" + "\n".join(errors) + "\n\nworker log tail:\n"
            + tail(worker["log"], 3000))


_observed: dict = {}


@pytest.mark.timeout(WAIT_S + 120)
def test_scheduler_creates_runs_that_a_process_worker_completes(prefect_server,
                                                                scheduled_deployment, worker):
    from prefect.client.orchestration import get_client

    dep_id = scheduled_deployment["id"]
    with get_client(sync_client=True) as client:
        dep = client.read_deployment(dep_id)
    assert dep.work_pool_name == POOL and len(dep.schedules) == 1 and dep.schedules[0].active
    assert dep.schedules[0].schedule.interval.total_seconds() == INTERVAL_S

    # nothing but the server's scheduler creates runs of this deployment (no run_deployment)
    deadline = time.monotonic() + WAIT_S
    first = None
    while first is None:
        assert worker["proc"].poll() is None, f"worker exited:\n{tail(worker['log'])}"
        runs = _runs_of(dep_id)
        if runs:
            first = runs[0]
        elif time.monotonic() > deadline:
            pytest.fail(f"the server's scheduler created no run of the deployment in {WAIT_S} s"
                        f"\n{_diagnostics(prefect_server, worker)}")
        else:
            time.sleep(2)
    assert first.auto_scheduled and "auto-scheduled" in first.tags
    assert first.created_by is not None and first.created_by.type == "SCHEDULE"
    assert first.work_pool_name == POOL

    # that run, scheduled by the server, is run to completion by the worker
    while True:
        with get_client(sync_client=True) as client:
            run = client.read_flow_run(first.id)
        if run.state is not None and run.state.is_final():
            break
        assert worker["proc"].poll() is None, f"worker exited:\n{tail(worker['log'])}"
        if time.monotonic() > deadline:
            pytest.fail(f"scheduled run {run.name} is {run.state} after {WAIT_S} s\n"
                        f"{_diagnostics(prefect_server, worker)}")
        time.sleep(2)
    with get_client(sync_client=True) as client:
        history = client.read_flow_run_states(run.id)
    assert run.state.is_completed(), (f"scheduled run {run.name} ended {run.state}\n"
                                      f"{_diagnostics(prefect_server, worker)}")
    assert history[0].type.value == "SCHEDULED" and history[0].message == "Flow run scheduled"
    assert [s.type.value for s in history][-1] == "COMPLETED"
    # the worker really ran the flow's code, in a process of its own
    assert (scheduled_deployment["out"] / f"{run.id}.done").read_text() == run.name
    _observed["completed"] = run


def _flow_run_ls(prefect_server, *args: str) -> str:
    env = dict(prefect_server["env"], COLUMNS="250")  # a wide table: no cell is cut
    proc = subprocess.run([str(PREFECT), "flow-run", "ls", *args], env=env, capture_output=True,
                          text=True, timeout=100)
    assert proc.returncode == 0, (f"prefect flow-run ls {' '.join(args)} exited "
                                  f"{proc.returncode}:\n{proc.stdout}\n{proc.stderr}")
    assert "Flow Runs" in proc.stdout, proc.stdout
    return proc.stdout


@pytest.mark.timeout(120)
def test_flow_run_ls_lists_the_completed_scheduled_run(prefect_server):
    _flow_run_ls(prefect_server)  # the plain listing first: needs no completed run
    run = _observed.get("completed")
    if run is None:
        pytest.fail("no completed scheduled run (the scheduler test failed or did not run)")
    out = _flow_run_ls(prefect_server, "--state-type", "COMPLETED", "--flow-name", FLOW_NAME)
    assert run.name in out, out
    line = next(ln for ln in out.splitlines() if run.name in ln)
    assert str(run.id) in line and FLOW_NAME in line and "COMPLETED" in line, line
