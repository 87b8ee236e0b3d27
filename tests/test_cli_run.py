"""`hmflow run` and `hmflow report` as a user types them (real OPM, real Prefect, real files).

The commands use the session's Prefect server (conftest.prefect_api) instead of starting one
each: the temporary server itself is tested in test_signals and test_prefect_server."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from conftest import cli_env
from typer.testing import CliRunner

pytestmark = pytest.mark.opm

DIAGNOSIS_BUDGET = 8
"""The minimum of a diagnosis of the small synthetic case from a campaign's best with
``--kinds aquifer_strength`` (1 run of the best, 2 probes, 5 finite differences)."""


def hmflow(*args: str, cwd: Path, api: str | None = None,
           timeout: int = 600) -> subprocess.CompletedProcess:
    env = cli_env(api, COLUMNS="150") if api else {**os.environ, "COLUMNS": "150"}
    return subprocess.run([sys.executable, "-m", "hmflow.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


def in_process(*args: str, api: str):
    """`hmflow ARGS` run in this process (for a command refused before any flow starts, with
    the session's Prefect server as its API): its result and its stderr with runs of white
    space as one space."""
    from hmflow.cli import app

    out = CliRunner().invoke(app, list(args), env={"PREFECT_API_URL": api, "COLUMNS": "150"})
    return out, " ".join(out.stderr.split())


def test_run_on_the_synthetic_default_then_report_only(tmp_path, prefect_api, restore_env):
    run = hmflow("run", "--budget", "2", "--workers", "2", "--agent", "random", "--seed", "3",
                 cwd=tmp_path, api=prefect_api)
    assert run.returncode == 0, run.stdout + run.stderr
    out = run.stdout
    assert "campaign synthetic-random-seed3" in out
    assert "2/2" in out                                   # the progress bar reached the budget
    assert "best call" in out and "truth" in out          # best parameters and distance to truth
    assert "match by category" in out and "C_match (%) per well" in out
    storage = tmp_path / "hmflow-storage" / "synthetic-random-seed3"   # the default storage
    assert len(list((storage / "evaluations").glob("*.json"))) == 2
    runs_before = sorted(p.name for p in (storage / "runs").iterdir())

    rep = hmflow("report", "--storage", str(tmp_path / "hmflow-storage"), "--campaign",
                 "synthetic-random-seed3", cwd=tmp_path, api=prefect_api)
    assert rep.returncode == 0, rep.stdout + rep.stderr
    assert "best call" in rep.stdout
    assert sorted(p.name for p in (storage / "runs").iterdir()) == runs_before
    doc = json.loads(sorted((storage / "report").glob("v*/report.json"))[-1].read_text())
    assert doc["calls"] == 2 and set(doc["truth_distance"]) == {
        "poro_mult", "permx_mult", "permy_mult", "permz_mult", "skin"}

    # a diagnosis of this campaign starts from its best on its own case: another is refused
    # before any simulation (a broken case with its own errors, a valid one as a different
    # case); both before any flow starts, so in this process
    bad = tmp_path / "bad.toml"
    bad.write_text('[case]\nname = "x"\ndeck = "missing.DATA"\nobserved = "missing.csv"\n')
    store_args = ("--storage", str(tmp_path / "hmflow-storage"))
    refused, said = in_process("diagnose", "--from-campaign", "synthetic-random-seed3",
                               "--case", str(bad), *store_args, api=prefect_api)
    assert refused.exit_code == 2 and "deck file not found" in said, refused.output
    source = Path(json.loads(sorted((storage / "case").glob("v*/case.json"))[-1].read_text())
                  ["source"])
    shutil.copytree(source.parent, tmp_path / "copy")
    toml = tmp_path / "copy" / source.name
    toml.write_text(toml.read_text().replace("time_tolerance_days = 30", "time_tolerance_days = 20")
                    if "time_tolerance_days" in toml.read_text() else
                    toml.read_text().replace("[case]", "[case]\ntime_tolerance_days = 20"))
    refused, said = in_process("diagnose", "--from-campaign", "synthetic-random-seed3",
                               "--case", str(toml), *store_args, api=prefect_api)
    assert refused.exit_code == 2, refused.output
    assert "calibrated on the case" in said and "case_file" in said, refused.output
    assert not (storage / "diagnosis-runs").exists()


def test_report_for_an_unknown_campaign_is_a_clear_error(tmp_path):
    (tmp_path / "store").mkdir()
    rep = hmflow("report", "--storage", str(tmp_path / "store"), "--campaign", "nope", cwd=tmp_path)
    assert rep.returncode == 2 and "no campaign 'nope'" in rep.stderr


def test_run_on_a_bad_case_fails_before_any_simulation(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[case]\nname = "x"\ndeck = "missing.DATA"\nobserved = "missing.csv"\n')
    run = hmflow("run", "--case", str(bad), "--budget", "2", cwd=tmp_path)
    assert run.returncode == 2
    assert "deck file not found" in run.stderr and "observed history file not found" in run.stderr
    assert not (tmp_path / "hmflow-storage").exists()


def test_diagnose_on_a_bad_case_or_a_missing_campaign_fails_before_any_simulation(tmp_path,
                                                                                 prefect_api):
    bad = tmp_path / "bad.toml"
    bad.write_text('[case]\nname = "x"\ndeck = "missing.DATA"\nobserved = "missing.csv"\n')
    run = hmflow("diagnose", "--case", str(bad), cwd=tmp_path, api=prefect_api)
    assert run.returncode == 2 and "deck file not found" in run.stderr
    run = hmflow("diagnose", "--from-campaign", "nope", "--storage", str(tmp_path / "store"),
                 cwd=tmp_path, api=prefect_api)
    assert run.returncode == 2 and "no archived best case of campaign 'nope'" in run.stderr
    assert not (tmp_path / "hmflow-storage").exists() and not (tmp_path / "store").exists()


def test_diagnose_from_a_campaign_goes_into_its_report_and_the_campaign_still_resumes(
        tmp_path, small_case, prefect_api):
    """`hmflow run` on a case file -> `hmflow diagnose --from-campaign` (its best, its case, no
    new case version) -> `hmflow run` resumes the same campaign; its report holds both parts
    (real OPM, real Prefect, real files; the small synthetic case, conftest.small_case). The
    diagnosis's budget as the user types it: one under the minimum is refused in one line
    before any simulation; one that covers the minimum of the kinds asked for spends exactly
    as many simulations as run directories, never more than the budget, with the workers and
    kinds given."""
    shutil.copytree(small_case.parent, tmp_path / "syn")
    args = ("--case", "syn/case.toml", "--agent", "random", "--seed", "1", "--workers", "2",
            "--campaign", "rel")
    run = hmflow("run", "--budget", "2", *args, cwd=tmp_path, api=prefect_api)
    assert run.returncode == 0, run.stdout + run.stderr
    campaign = tmp_path / "hmflow-storage" / "rel"
    runs = campaign / "diagnosis-runs"
    refused = hmflow("diagnose", "--from-campaign", "rel", "--budget", "8", cwd=tmp_path,
                     api=prefect_api)
    assert refused.returncode == 2, refused.stdout + refused.stderr
    lines = [ln for ln in refused.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "--budget: 8 simulator calls cannot cover the minimum of 40" \
        in lines[0], refused.stderr
    assert "Traceback" not in refused.stdout + refused.stderr
    assert not runs.exists()
    # one family of candidates, the least budget it allows (its minimum: the best's run, one
    # probe and the ranking's differences): this test is about where the diagnosis goes and
    # what it spends, not what it finds (test_diagnosis_hidden is)
    diag = hmflow("diagnose", "--from-campaign", "rel", "--kinds", "aquifer_strength",
                  "--budget", str(DIAGNOSIS_BUDGET), "--workers", "2", cwd=tmp_path,
                  api=prefect_api, timeout=1200)
    assert diag.returncode == 0, diag.stdout + diag.stderr
    assert "Traceback" not in diag.stdout + diag.stderr
    assert [p.name for p in (campaign / "case").glob("v*")] == ["v0001"]  # the campaign's own
    assert (campaign / "diagnosis-report").is_dir()
    doc = json.loads(sorted((campaign / "diagnosis-report").glob("v*/diagnosis.json"))[-1]
                     .read_text())
    assert doc["settings"]["kinds"] == ["aquifer_strength"] and doc["settings"]["workers"] == 2
    assert {c["kind"] for c in doc["ranking"]["candidates"]} == {"aquifer_strength"}
    made = len([p for p in runs.iterdir() if p.is_dir()])
    assert doc["cost"]["simulations"] == made <= DIAGNOSIS_BUDGET
    report = sorted((campaign / "report").glob("v*/report.md"))[-1].read_text()
    assert "## Best case" in report and "## Diagnosis of case `synthetic-small`" in report
    # the noise the fit weighed, stored with the case and shown in the report
    noise = pd.read_parquet(campaign / "case" / "v0001" / "noise.parquet")
    assert set(noise.quantity) >= {"WBHP", "WOPR"}
    assert "## The noise the fit assumed" in report
    assert all(f"| {q} | " in report for q in set(noise.quantity)), report
    # the same budget again: the resume is accepted (a larger one extends the campaign:
    # test_campaign.test_rerun_resumes_and_extends_without_resimulating)
    again = hmflow("run", "--budget", "2", *args, cwd=tmp_path, api=prefect_api)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "resuming campaign rel: 2 calls already journaled" in again.stdout + again.stderr
    assert len(list((campaign / "evaluations").glob("*.json"))) == 2
