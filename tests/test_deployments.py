"""The scheduled campaign deployment for real: a `prefect server start` (SQLite, temporary
PREFECT_HOME, free loopback port: the session's, conftest.prefect_server), a process work pool, the deployments of
``deployments/campaign.py``, a `prefect worker start` subprocess and real OPM Flow runs.

The campaign (the small synthetic case of conftest.small_case, random agent, budget 2, 2 at
a time) is triggered with ``run_deployment``; then the report-only deployment is run and must
not simulate anything. The ensemble deployment (the field version of the small case,
tests/test_ensemble_flow.py's ``field_case``) is deployed and read back from the server, not
run: its flow is the one tests/test_ensemble_flow.py runs, and its report rerun is the same
report-only flow (``hmflow report`` rebuilds an ensemble's report there).
Server, worker and every process they started are stopped in the fixtures' teardown.
"""

from __future__ import annotations


import datetime as dt
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from prefect_processes import PREFECT, serve_worker, tail
from test_ensemble_flow import field_case
from typer.testing import CliRunner

from hmcore.cases import load_case
from hmflow.cli import app

REPO = Path(__file__).resolve().parents[1]
POOL = "hmflow-test-process"
NAME = "it-nightly"
CAMPAIGN = "deploy-it"
BUDGET = 2
RUN_TIMEOUT_S = 240

pytestmark = [
    pytest.mark.opm,
    pytest.mark.skipif(not PREFECT.is_file(), reason=f"prefect CLI not found at {PREFECT}"),
]


@pytest.fixture(scope="module")
def api_settings(prefect_server):
    """Point this test process's Prefect client at the test server (and the temporary home)."""
    from prefect.settings import PREFECT_API_URL, PREFECT_HOME, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: prefect_server["api"],
                                     PREFECT_HOME: str(prefect_server["home"])}):
        yield prefect_server


@pytest.fixture(scope="module")
def deployed(api_settings, tmp_path_factory, small_case):
    """The process pool and both deployments (campaign on a cron schedule, report-only)."""
    from deployments.campaign import (campaign_parameters, deploy_campaign, deploy_report,
                                      ensure_work_pool)

    tmp = tmp_path_factory.mktemp("deploy")
    case = small_case
    storage = tmp / "store"
    # a daily cron 12 h away from now: never due while this test runs
    cron = f"0 {(dt.datetime.now(dt.timezone.utc).hour + 12) % 24} * * *"
    pool = ensure_work_pool(POOL)
    assert ensure_work_pool(POOL).id == pool.id  # idempotent
    # seed 1: a call within the budget that no physics check penalises, so a best case is
    # archived (seed 0's first four are all penalised on this case)
    params = campaign_parameters(case=str(case), agent="random", budget=BUDGET, workers=2,
                                 seed=1, storage=storage, campaign=CAMPAIGN)
    assert params["storage"] == str(storage.resolve()) and Path(params["storage"]).is_absolute()
    campaign_id = deploy_campaign(NAME, cron=cron, timezone="UTC", parameters=params,
                                  work_pool=POOL)
    report_id = deploy_report(NAME, storage=storage, campaign=CAMPAIGN, work_pool=POOL)
    return {"pool": pool, "cron": cron, "params": params, "storage": storage.resolve(),
            "campaign_id": campaign_id, "report_id": report_id}


@pytest.fixture(scope="module")
def worker(prefect_server, deployed):
    with serve_worker(prefect_server, POOL, "hmflow-it-worker") as w:
        yield w


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------
def _run(deployment: str, worker: dict, timeout: int = RUN_TIMEOUT_S):
    from prefect.deployments import run_deployment

    assert worker["proc"].poll() is None, f"worker exited:\n{tail(worker['log'])}"
    t0 = time.monotonic()
    flow_run = run_deployment(deployment, timeout=timeout, poll_interval=2)
    elapsed = time.monotonic() - t0
    assert flow_run.state is not None and flow_run.state.is_completed(), (
        f"{deployment}: flow run {flow_run.id} is {flow_run.state} after {elapsed:.0f} s "
        f"(limit {timeout} s)\nworker log:\n{tail(worker['log'])}")
    return flow_run


def _artifacts_of(flow_run_id) -> list:
    """Artifacts of a flow run. Every filter, sort, limit and offset is given: with fastapi 0.151
    or later the server refuses the nulls that ``read_artifacts()`` sends for the ones left out
    (422); fastapi is pinned below 0.151, and the explicit query keeps working either way."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, FlowRunFilter, FlowRunFilterId
    from prefect.client.schemas.sorting import ArtifactSort

    with get_client(sync_client=True) as client:
        return client.read_artifacts(
            artifact_filter=ArtifactFilter(),
            flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[flow_run_id])),
            sort=ArtifactSort.KEY_ASC, limit=50, offset=0)  # no task-run filter: it would
        #   leave out the artifacts made by the flow itself (the progress), not by a task


def _journal(storage: Path) -> list[dict]:
    return [json.loads(p.read_text())
            for p in sorted((storage / CAMPAIGN / "evaluations").glob("*.json"))]


def _run_dirs(storage: Path) -> list[str]:
    runs = storage / CAMPAIGN / "runs"
    return sorted(p.name for p in runs.iterdir()) if runs.is_dir() else []


# --------------------------------------------------------------------------------------------
# tests
# --------------------------------------------------------------------------------------------
@pytest.mark.timeout(600)
def test_scheduled_campaign_deployment_runs_on_a_process_worker(deployed, worker):
    from prefect.client.orchestration import get_client

    from storage import ArtifactStore

    # the deployments as registered
    with get_client(sync_client=True) as client:
        dep = client.read_deployment(deployed["campaign_id"])
        rep = client.read_deployment(deployed["report_id"])
        pool = client.read_work_pool(POOL)
    assert pool.type == "process"
    assert dep.name == NAME and dep.work_pool_name == POOL
    assert len(dep.schedules) == 1 and dep.schedules[0].active
    assert dep.schedules[0].schedule.cron == deployed["cron"]
    assert dep.schedules[0].schedule.timezone == "UTC"
    assert dep.parameters == deployed["params"]
    assert dep.pull_steps == [{"prefect.deployments.steps.set_working_directory":
                               {"directory": str(REPO)}}]
    assert rep.work_pool_name == POOL and not rep.schedules
    assert rep.parameters == {"storage": str(deployed["storage"]), "campaign": CAMPAIGN}

    # the campaign, triggered now, run by the worker
    flow_run = _run(f"hmflow-campaign/{NAME}", worker)
    storage = deployed["storage"]
    store = ArtifactStore(storage)
    rows = _journal(storage)
    assert [r["index"] for r in rows] == list(range(BUDGET))
    for step in ("case", "results", "best", "report"):
        assert store.latest(CAMPAIGN, step) is not None, f"no {step} version in {storage}"
    table = store.latest(CAMPAIGN, "results").read_parquet("evaluations.parquet")
    assert len(table) == BUDGET
    assert store.latest(CAMPAIGN, "report").file("report.md").read_text().strip()
    assert len(_run_dirs(storage)) == BUDGET

    keys = {a.key for a in _artifacts_of(flow_run.id)}
    assert {f"{CAMPAIGN}-report", f"{CAMPAIGN}-categories", f"{CAMPAIGN}-wells",
            f"{CAMPAIGN}-ratios", f"{CAMPAIGN}-progress", f"{CAMPAIGN}-report-file"} <= keys, keys
    arts = {a.key: a for a in _artifacts_of(flow_run.id)}
    assert arts[f"{CAMPAIGN}-report"].type == "markdown" and arts[f"{CAMPAIGN}-wells"].type == "table"
    assert arts[f"{CAMPAIGN}-progress"].type == "progress"
    assert float(arts[f"{CAMPAIGN}-progress"].data) == 100.0
    assert f"{BUDGET}/{BUDGET} calls" in arts[f"{CAMPAIGN}-progress"].description
    assert arts[f"{CAMPAIGN}-report-file"].type == "markdown"  # a link artifact renders as one
    # the UI tells what is happening: the run is named after the campaign, tagged, and its
    # simulator task runs carry their call numbers
    with get_client(sync_client=True) as client:
        run = client.read_flow_run(flow_run.id)
        from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
        tasks = client.read_task_runs(flow_run_filter=FlowRunFilter(
            id=FlowRunFilterId(any_=[flow_run.id])), limit=100)
    assert run.name.startswith(f"{CAMPAIGN}-"), run.name
    assert {"case:synthetic-small", "agent:random", "seed:1"} <= set(run.tags), run.tags
    sims = sorted(t.name for t in tasks if t.name.startswith("sim-"))
    assert sims == [f"sim-{i:03d}" for i in range(1, BUDGET + 1)], [t.name for t in tasks]

    # the report-only deployment: a new report from stored artifacts, no simulator call
    journal_before = [(r["index"], r["run_dir"]) for r in rows]
    runs_before = _run_dirs(storage)
    report_run = _run(f"hmflow-report/{NAME}", worker, timeout=120)
    assert [(r["index"], r["run_dir"]) for r in _journal(storage)] == journal_before
    assert _run_dirs(storage) == runs_before
    assert store.latest(CAMPAIGN, "report").read_json("report.json")["calls"] == BUDGET
    keys = {a.key for a in _artifacts_of(report_run.id)}
    assert {f"{CAMPAIGN}-report", f"{CAMPAIGN}-categories", f"{CAMPAIGN}-wells"} <= keys, keys
    assert "Traceback" not in tail(worker["log"], 100_000)


@pytest.mark.timeout(120)
def test_cli_creates_pool_and_both_deployments(prefect_server, tmp_path):
    """`python -m deployments.campaign` against the same server (no flow is run here)."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    pool = "hmflow-cli-pool"
    proc = subprocess.run(
        [sys.executable, "-m", "deployments.campaign", "--pool", pool, "--name", "cli-check",
         "--cron", "30 3 * * 1", "--timezone", "Europe/Oslo", "--agent", "random",
         "--budget", "3", "--storage", "rel-store", "--campaign", "cli-campaign"],
        cwd=tmp_path, env=prefect_server["env"], capture_output=True, text=True, timeout=100)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "hmflow-campaign/cli-check" in proc.stdout
    assert "hmflow-report/cli-check-report" in proc.stdout  # its own name in the UI
    with temporary_settings(updates={PREFECT_API_URL: prefect_server["api"]}):
        with get_client(sync_client=True) as client:
            assert client.read_work_pool(pool).type == "process"
            dep = client.read_deployment_by_name("hmflow-campaign/cli-check")
            rep = client.read_deployment_by_name("hmflow-report/cli-check-report")
    assert dep.schedules[0].schedule.cron == "30 3 * * 1"
    assert dep.schedules[0].schedule.timezone == "Europe/Oslo"
    assert dep.parameters["storage"] == str((tmp_path / "rel-store").resolve())
    assert dep.parameters["case"] == "synthetic" and dep.parameters["budget"] == 3
    assert rep.parameters == {"storage": str((tmp_path / "rel-store").resolve()),
                              "campaign": "cli-campaign"}


def test_cli_refuses_a_missing_case_file(prefect_server, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "deployments.campaign", "--case",
                           str(tmp_path / "nope.toml")], cwd=tmp_path, env=prefect_server["env"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "not found" in proc.stderr


def test_cli_refuses_to_deploy_without_a_configured_server(prefect_server, tmp_path):
    env = {k: v for k, v in prefect_server["env"].items() if k != "PREFECT_API_URL"}
    env["PREFECT_HOME"] = str(tmp_path / "home")  # a profile without PREFECT_API_URL
    proc = subprocess.run([sys.executable, "-m", "deployments.campaign"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "PREFECT_API_URL" in proc.stderr, proc.stderr


@pytest.mark.timeout(180)
def test_hmflow_deploy_interval_and_list(prefect_server, tmp_path):
    """`hmflow deploy` (the CLI users are told to use): an interval schedule, the report-only
    deployment under its own name, tags, and `--list`; a bad agent is refused before deploying."""
    env = dict(prefect_server["env"], COLUMNS="250")

    def hmflow(*args):
        return subprocess.run([sys.executable, "-m", "hmflow.cli", *args], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=120)

    bad = hmflow("deploy", "--name", "x", "--agent", "ppo")
    assert bad.returncode == 2 and "--agent must be one of" in bad.stderr
    ok = hmflow("deploy", "--name", "hourly", "--pool", "hmflow-deploy-pool", "--interval",
                "3600", "--agent", "cmaes", "--budget", "8", "--storage", "s")
    assert ok.returncode == 0, ok.stdout + ok.stderr
    assert "hmflow-campaign/hourly" in ok.stdout and "every 3600 s" in ok.stdout
    assert "hmflow-report/hourly-report" in ok.stdout
    listed = hmflow("deploy", "--list")
    assert listed.returncode == 0, listed.stdout + listed.stderr
    lines = [line for line in listed.stdout.splitlines() if "hourly" in line]
    assert any("hmflow-campaign/hourly" in line and "every 3600 s" in line and "cmaes" in line
               for line in lines), listed.stdout
    assert any("hmflow-report/hourly-report" in line and "none" in line for line in lines)
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: prefect_server["api"]}):
        with get_client(sync_client=True) as client:
            dep = client.read_deployment_by_name("hmflow-campaign/hourly")
    assert dep.schedules[0].schedule.interval.total_seconds() == 3600
    assert {"hmflow", "case:synthetic", "agent:cmaes"} <= set(dep.tags)
    assert dep.parameters["agent"] == "cmaes" and dep.parameters["budget"] == 8


# --------------------------------------------------------------------------------------------
# the ensemble deployment: deployed and read back, not run (suite time)
# --------------------------------------------------------------------------------------------
ENSEMBLE_POOL = "hmflow-ensemble-pool"


@pytest.fixture(scope="module")
def ensemble_case(tmp_path_factory, small_case) -> Path:
    """The field version of the small case (two fields, no scalar parameter), 2 members."""
    case, _ = field_case(tmp_path_factory.mktemp("ensemble-deploy") / "case", small_case,
                         "never-fails", "size = 2\nweights = [1.0]\nmin_realizations = 2\n")
    return case


def _deployment(name: str):
    """The deployment ``flow/name`` on the test server, or None when there is none."""
    from prefect.client.orchestration import get_client
    from prefect.exceptions import ObjectNotFound

    with get_client(sync_client=True) as client:
        try:
            return client.read_deployment_by_name(name)
        except ObjectNotFound:
            return None


def _deploy(*args: str):
    return CliRunner().invoke(app, ["deploy", *args], env={"COLUMNS": "250", "NO_COLOR": "1"})


@pytest.mark.timeout(120)
def test_ensemble_deployment_runs_the_ensemble_flow_from_this_checkout(
        api_settings, ensemble_case, tmp_path, monkeypatch):
    from prefect.client.orchestration import get_client

    from deployments.campaign import deploy_ensemble, ensemble_parameters
    from flows.ensemble import default_ensemble_name

    monkeypatch.chdir(ensemble_case.parent.parent)  # relative paths, made absolute
    params = ensemble_parameters(case=f"case/{ensemble_case.name}", workers=2, storage="store")
    assert params == {"case": str(ensemble_case.resolve()), "workers": 2,
                      "storage": str((ensemble_case.parent.parent / "store").resolve()),
                      "campaign": default_ensemble_name(load_case(ensemble_case).name)}
    assert params["campaign"] == "synthetic-small-ensemble"  # the name `hmflow ensemble` gives
    dep_id = deploy_ensemble("ens-py", params, cron="0 4 * * 1", work_pool=ENSEMBLE_POOL)
    with get_client(sync_client=True) as client:
        dep = client.read_deployment(dep_id)
        flow = client.read_flow(dep.flow_id)
    assert flow.name == "hmflow-ensemble" and dep.entrypoint == "flows/ensemble.py:ensemble_flow"
    assert dep.parameters == params and dep.work_pool_name == ENSEMBLE_POOL
    # every stored parameter is one of the flow's (the server checks a run's against these)
    assert set(params) <= set(dep.parameter_openapi_schema["properties"])
    assert dep.pull_steps == [{"prefect.deployments.steps.set_working_directory":
                               {"directory": str(REPO)}}]
    assert dep.schedules[0].schedule.cron == "0 4 * * 1"
    assert dep.global_concurrency_limit.limit == 1  # two runs never work on one ensemble
    assert {"hmflow", "ensemble"} <= set(dep.tags)


@pytest.mark.timeout(120)
def test_hmflow_deploy_chooses_the_ensemble_flow_for_a_case_of_fields(
        api_settings, ensemble_case, tmp_path, restore_env):
    storage = tmp_path / "store"
    out = _deploy("--case", str(ensemble_case), "--name", "ens", "--pool", ENSEMBLE_POOL,
                  "--interval", "86400", "--workers", "3", "--storage", str(storage))
    assert out.exit_code == 0, out.output
    text = " ".join(out.output.split())
    assert "deployment 'hmflow-ensemble/ens'" in text and "every 86400 s" in text
    assert "has field parameters poro, permx" in text and "2 members, weights [1.0]" in text
    dep, rep = _deployment("hmflow-ensemble/ens"), _deployment("hmflow-report/ens-report")
    assert _deployment("hmflow-campaign/ens") is None
    assert dep.entrypoint == "flows/ensemble.py:ensemble_flow"
    assert dep.parameters == {"case": str(ensemble_case.resolve()), "workers": 3,
                              "storage": str(storage.resolve()),
                              "campaign": "synthetic-small-ensemble"}
    assert dep.schedules[0].schedule.interval.total_seconds() == 86400
    assert {"hmflow", "ensemble", "case:synthetic-small"} <= set(dep.tags)
    assert not {t for t in dep.tags if t.startswith("agent:")}
    # the report-only rerun: the same flow as a campaign's, on the ensemble's name
    assert rep.entrypoint == "flows/report.py:report_flow"
    assert rep.parameters == {"storage": str(storage.resolve()),
                              "campaign": "synthetic-small-ensemble"}

    listed = _deploy("--list")
    assert listed.exit_code == 0, listed.output
    row = next(line for line in listed.output.splitlines() if "hmflow-ensemble/ens " in line)
    cells = [c.strip() for c in row.split("│") if c.strip()]
    assert cells[4:] == ["synthetic-small-ensemble", "-", "-"], row  # campaign, agent, budget


@pytest.mark.timeout(120)
def test_hmflow_deploy_refuses_an_ensemble_with_campaign_options_before_deploying(
        api_settings, ensemble_case, small_case, restore_env):
    from prefect.client.orchestration import get_client
    from prefect.exceptions import ObjectNotFound

    pool = "hmflow-refused-pool"
    out = _deploy("--case", str(ensemble_case), "--name", "refused", "--pool", pool,
                  "--agent", "lm", "--seed", "3", "--cron", "0 1 * * *", "--interval", "60")
    assert out.exit_code == 2, out.output
    text = " ".join(out.output.split())
    # every problem at once, one line each
    assert "give --cron or --interval, not both" in text
    assert ("--agent, --seed do not apply to an ensemble deployment (case synthetic-small has "
            "field parameters poro, permx -> the ensemble flow") in text
    assert "--budget" not in text  # only the options given are named
    assert "--flow campaign" not in text  # the case has no scalar parameter to calibrate
    assert _deployment("hmflow-ensemble/refused") is None
    assert _deployment("hmflow-report/refused-report") is None
    with get_client(sync_client=True) as client, pytest.raises(ObjectNotFound):
        client.read_work_pool(pool)  # not even the pool

    # an explicit flow is held to that flow's rules of the case
    fields_as_campaign = _deploy("--case", str(ensemble_case), "--flow", "campaign",
                                 "--pool", pool)
    assert fields_as_campaign.exit_code == 2
    assert "has field parameters only (poro, permx)" in " ".join(
        fields_as_campaign.output.split())
    scalars_as_ensemble = _deploy("--case", str(small_case), "--flow", "ensemble", "--pool",
                                  pool, "--budget", "4")
    assert scalars_as_ensemble.exit_code == 2
    text = " ".join(scalars_as_ensemble.output.split())
    assert "has no field parameter for an ensemble to match" in text
    assert "--budget does not apply to an ensemble deployment" in text
    assert "or give --flow campaign" in text  # the small case has scalar parameters
    unknown = _deploy("--case", str(ensemble_case), "--flow", "esmda", "--pool", pool)
    assert unknown.exit_code == 2
    assert "--flow must be one of ['campaign', 'ensemble'], got 'esmda'" in unknown.output
    with get_client(sync_client=True) as client, pytest.raises(ObjectNotFound):
        client.read_work_pool(pool)
