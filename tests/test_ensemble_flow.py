"""The ensemble flow end to end with the real simulator and real Prefect, on a field version of
the small synthetic case (conftest.small_case: 10 x 10 x 5 cells, 4 wells, 3 years): a PORO
field drawn per layer with gstools and a PERMX (= PERMY) field from it, 8 members, 2
assimilations, the member runs on a two-worker Dask cluster. The simulator is OPM Flow behind a command template that logs every call and
fails member 5 of the prior (a real non-zero exit), so the flow must leave it out of the
updates and go on; the run's report (maps, wells, misfit boxes, fans) is stored and rebuilt
by ``hmflow report`` with no simulator call; and a run where every member fails stops with
one line."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from conftest import cli_env
from test_cluster import DASK, _worker_pids, dask_cluster
from test_ensemble_report import drawn

from hmcore.cases import load_case
from hmcore.fields.grdecl import read_grdecl
from hmcore.fields.grid import read_grid
from hmcore.fields.layout import Layout
from hmcore.fields.members import INCLUDE_NAME, ensemble_matrix
from hmcore.fields.transform import to_physical
from hmcore.scenarios.synthetic_fields import FIELDS
from storage import ArtifactStore, EvaluationJournal
from storage.ensemble import (
    ENSEMBLE_FILE,
    FORECAST_STEP,
    REPORT_STEP,
    ensemble_step,
    member_journal,
)

pytestmark = [pytest.mark.opm]
SIZE, FAILED = 8, 5
WRAPPER = """#!/usr/bin/env bash
# DECK RUN_DIR PYTHON LOG PATTERN: log the run, exit 7 when its folder matches PATTERN, else OPM
set -u
name=$(basename "$2")
echo "$name" >> "$4"
case "$name" in $5) echo "injected failure of $name" >&2; exit 7;; esac
exec "$3" -m hmcore.simulation.opm_runner "$1" "$2"
"""


def field_case(folder: Path, small_case: Path, fail: str, ensemble: str) -> tuple[Path, Path]:
    """A copy of the small case with the two fields, the logging (and failing) simulator and
    ``ensemble`` as its [ensemble] section; returns (case.toml, the simulator's log)."""
    shutil.copytree(small_case.parent, folder, ignore=shutil.ignore_patterns("truth*"))
    script, log = folder / "simulator.sh", folder / "simulator.log"
    script.write_text(WRAPPER)
    template = f"bash {script} {{deck}} {{run_dir}} {sys.executable} {log} {fail}"
    case = folder / "case.toml"
    case.write_text(case.read_text() + f'\n[simulator]\nbackend = "{template}"\n'
                    f"timeout_s = 300\n{FIELDS}\n[ensemble]\n{ensemble}\n")
    return case, log


@pytest.fixture(scope="module")
def run(tmp_path_factory, small_case):
    """The run every test here reads, on a Dask cluster (a `dask scheduler` and two `dask
    worker` processes, tests/test_cluster.py's): the member runs go to the workers, as a
    user's would with ``--task-runner dask``."""
    from flows.ensemble import ensemble_flow

    if not DASK.exists():
        pytest.skip("the dask command is not installed")
    tmp = tmp_path_factory.mktemp("ensemble")
    case, log = field_case(tmp / "case", small_case, f"i00-m{FAILED:04d}",
                           f"size = {SIZE}\nweights = [2.0, 1.0]\nmin_realizations = 4\n")
    storage = tmp / "store"
    (tmp / "dask").mkdir()
    with dask_cluster(tmp / "dask") as cluster:
        pids = set(_worker_pids(cluster["address"]).values())
        result = ensemble_flow(case=str(case), workers=2, storage=str(storage), campaign="e",
                               task_runner="dask", dask_address=cluster["address"])
    return {"case": case, "log": log, "store": ArtifactStore(storage), "result": result,
            "worker_pids": pids}


def ensembles(run) -> list[np.ndarray]:
    layout = Layout(("poro", "permx"), (), 500)
    return [ensemble_matrix(run["store"].latest("e", ensemble_step(i)).read_parquet(
        ENSEMBLE_FILE), layout) for i in range(3)]


def test_every_ensemble_is_stored_as_float32_members_by_parameters(run):
    store = run["store"]
    prior = store.latest("e", ensemble_step(0))
    table = prior.read_parquet(ENSEMBLE_FILE)
    assert table.shape == (2 * 500, 2 + SIZE)  # parameter, cell, one column per member
    assert all(table[f"m{m:04d}"].dtype == np.float32 for m in range(SIZE))
    doc = prior.read_json("ensemble.json")
    assert doc["seeds"] == {"poro": 11, "permx": 12} and doc["members"] == SIZE
    X0 = ensembles(run)[0]
    assert np.isfinite(X0).all()
    # log10 permeability from porosity by the stated relation, within its scatter
    resid = X0[:, 500:] - (-0.9 + 12.6 * X0[:, :500])
    assert abs(resid.mean()) < 0.05 and 0.15 < resid.std() < 0.25


def test_a_failed_member_is_recorded_with_its_kind_and_left_out_of_the_updates(run):
    store = run["store"]
    prior_runs = {r["index"]: r for r in EvaluationJournal(store, "e", member_journal(0)).rows()}
    assert sorted(prior_runs) == list(range(SIZE))
    assert prior_runs[FAILED]["status"] == "FAIL" and prior_runs[FAILED]["failure"] == "crash"
    assert all(r["status"] != "FAIL" for m, r in prior_runs.items() if m != FAILED)
    X0, X1, X2 = ensembles(run)
    ok = [m for m in range(SIZE) if m != FAILED]
    assert np.isnan(X1[FAILED]).all() and np.isnan(X2[FAILED]).all()
    assert np.isfinite(X1[ok]).all() and np.isfinite(X2[ok]).all()
    assert np.abs(X1[ok] - X0[ok]).max() > 1e-3 and np.abs(X2[ok] - X1[ok]).max() > 1e-3
    for i in (1, 2):  # the member left out is not run again
        assert EvaluationJournal(store, "e", member_journal(i)).indices() == ok
    doc = store.latest("e", ensemble_step(1)).read_json("ensemble.json")
    assert doc["left_out_now"] == [FAILED] and doc["active"] == ok


def test_every_member_runs_in_a_dask_worker(run):
    """Run by the cluster's workers, not by the flow's process."""
    records = [r for i in range(3) for r in EvaluationJournal(run["store"], "e",
                                                             member_journal(i)).rows()]
    assert len(records) == 22 and {r["host_pid"] for r in records} <= run["worker_pids"]
    assert os.getpid() not in run["worker_pids"]


def test_each_member_run_calls_the_simulator_once(run):
    calls = Counter(run["log"].read_text().split())
    expected = {f"i00-m{m:04d}" for m in range(SIZE)} | {
        f"i{i:02d}-m{m:04d}" for i in (1, 2) for m in range(SIZE) if m != FAILED}
    assert set(calls) == expected and set(calls.values()) == {1}
    assert run["result"]["runs"] == len(expected) == 22 and run["result"]["failed"] == 1


def test_the_member_runs_with_its_own_fields_after_the_decks_grid_edits(run):
    store = run["store"]
    record = EvaluationJournal(store, "e", member_journal(1)).get(2)
    run_dir = Path(record["run_dir"])
    deck = (run_dir / "SYNTH.DATA").read_text()
    include = deck.index(f"'{run_dir / INCLUDE_NAME}'")
    assert deck.index("COPY") < deck.index("AQUANCON") < include < deck.index("\nPROPS")
    case = load_case(run["case"])
    grid = read_grid(case.deck)
    written = read_grdecl(run_dir / INCLUDE_NAME)
    X1 = ensembles(run)[1]
    poro, permx = case.fields
    np.testing.assert_allclose(written["PORO"][grid.active], to_physical(X1[2, :500], poro),
                               rtol=1e-6)
    np.testing.assert_allclose(written["PERMY"], written["PERMX"])
    np.testing.assert_allclose(written["PERMX"][grid.active], to_physical(X1[2, 500:], permx),
                               rtol=1e-6)


def test_the_updates_bring_the_members_closer_to_the_history(run):
    doc = run["store"].latest("e", FORECAST_STEP).read_json("summary.json")
    misfit = [it["misfit_median"] for it in doc["iterations"]]
    assert misfit[2] < misfit[1] < misfit[0], misfit
    assert [u["alpha"] for u in doc["updates"]] == [3.0, 1.5]  # weights 2, 1: sum 1/alpha = 1
    assert doc["iterations"][0]["failed_by_kind"] == {"crash": 1}


def test_the_forecast_gives_p90_p50_p10_of_the_prior_and_the_posterior(run):
    version = run["store"].latest("e", FORECAST_STEP)
    table = version.read_parquet("forecast.parquet")
    for ensemble, members in (("prior", SIZE - 1), ("posterior", SIZE - 1)):
        rows = table[table.ensemble == ensemble]
        keys = set(zip(rows.well, rows.quantity))
        assert {("FIELD", "FOPT")} | {(w, "WOPT") for w in ("PROD1", "PROD2", "PROD3",
                                                            "PROD4")} <= keys
        assert (rows.members == members).all()
        assert (rows.P90 <= rows.P50).all() and (rows.P50 <= rows.P10).all()
    values = version.read_parquet("members.parquet")
    fopt = values[(values.ensemble == "posterior") & (values.quantity == "FOPT")]
    assert sorted(fopt.member) == [m for m in range(SIZE) if m != FAILED]
    assert "FOPT P90/P50/P10: prior" in run["result"]["summary"]


def test_a_rerun_of_a_finished_ensemble_simulates_nothing(run):
    from flows.ensemble import ensemble_flow

    before = run["log"].read_text()
    again = ensemble_flow(case=str(run["case"]), workers=2,
                          storage=str(run["store"].root), campaign="e")
    assert run["log"].read_text() == before
    assert again["posterior"] == run["result"]["posterior"]


REPORT_FIGURES = ({"misfit_boxes.png", "forecast_fans.png"}
                  | {f"well__PROD{w}.png" for w in range(1, 5)}
                  | {f"map__{f}__k{k:02d}.png" for f in ("poro", "permx") for k in range(1, 6)})


def test_the_report_is_stored_with_every_figure_drawn(run):
    version = run["store"].latest("e", REPORT_STEP)
    assert version is not None and version.verify() == []
    assert run["result"]["report_html"] == str(version.file("report.html"))
    pngs = {n for n in version.files if n.endswith(".png")}
    assert REPORT_FIGURES <= pngs, sorted(REPORT_FIGURES - pngs)
    assert [n for n in sorted(pngs) if not drawn(version.file(n).read_bytes())] == []
    html = version.file("report.html").read_text()
    assert [n for n in sorted(pngs) if f'data-figure="{n}"' not in html] == []
    markdown = version.file("report.md").read_text()
    assert "Truth: unknown" in markdown and "| posterior | 7 | 7 | 0 |" in markdown
    doc = version.read_json("report.json")
    assert doc["kind"] == "ensemble" and doc["failed"] == 1
    assert {(r["ensemble"], r["members"]) for r in doc["forecast"]} == {("prior", 7),
                                                                       ("posterior", 7)}


def test_hmflow_report_rebuilds_the_ensembles_report_with_no_simulator_call(run, prefect_api):
    before = run["log"].read_text()
    done = subprocess.run([sys.executable, "-m", "hmflow.cli", "report", "--campaign", "e",
                           "--storage", str(run["store"].root)], capture_output=True,
                          text=True, timeout=300, env=cli_env(prefect_api), check=False)
    out = " ".join((done.stdout + done.stderr).split())
    assert done.returncode == 0, out[-2000:]
    assert run["log"].read_text() == before
    version = run["store"].latest("e", REPORT_STEP)
    assert "report.html" in out and "posterior" in out and version.verify() == []
    first = run["store"].get("e", REPORT_STEP, 1)
    assert version.manifest["inputs_hash"] == first.manifest["inputs_hash"]
    # the same run and code: the stored report, reused (a commit made meanwhile is new code)
    same_code = version.manifest["code_version"] == first.manifest["code_version"]
    assert version.version == (1 if same_code else 2)


def test_too_few_members_left_stops_the_iteration_with_one_line(tmp_path, small_case,
                                                                prefect_api):
    case, log = field_case(tmp_path / "case", small_case, "i00-m000[0-2]",
                           "size = 4\nweights = [1.0]\nmin_realizations = 2\n")
    done = subprocess.run([sys.executable, "-m", "hmflow.cli", "ensemble", "--case", str(case),
                           "--storage", str(tmp_path / "store"), "--workers", "2"],
                          capture_output=True, text=True, timeout=300, env=cli_env(prefect_api),
                          check=False)
    out = " ".join((done.stdout + done.stderr).split())
    assert done.returncode != 0, out[-2000:]
    assert ("ES-MDA assimilation 1 of 1: 1 of 4 members have results (3 failed now, 0 left "
            "out before), fewer than min_realizations = 2; the iteration stops") in out
    assert "Traceback" not in out
    assert sorted(log.read_text().split()) == [f"i00-m{m:04d}" for m in range(4)]
    store = ArtifactStore(tmp_path / "store")
    assert store.latest("synthetic-small-ensemble", ensemble_step(1)) is None
