"""`hmflow bench` as a user types it: every method on a synthetic case with the real OPM
Flow, a real Prefect server, real Parquet files; then the benchmark exported, unpacked on
"another machine" and continued there with one more seed. The default run
benchmarks the small synthetic case (the session's, see conftest.small_case) through the
session's Prefect server: what is tested is the benchmark's bookkeeping, not the case."""

from __future__ import annotations

import json
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import cli_env

from flows.bench import bench_names
from hmcore.calibration.methods import AGENTS
from hmcore.reporting.benchmark import LEVELS, per_run, summary
from storage import ArtifactStore

pytestmark = pytest.mark.opm
BUDGET, SEEDS = 4, 1  # 4: the smallest budget every method runs (ES-MDA: 2 members, twice);
# one seed, then the continued run adds a second
METHODS = ("lm", "esmda")
"""The methods of the default run: a driver with Jacobian runs and an ensemble, the two ways a
call is not one proposal (every method, all of :data:`hmcore.calibration.methods.AGENTS`, is
the `-m slow` run; tests/test_methods.py holds every method to its budget without the
simulator); the continued run adds a seed of ``RESUMED``."""
RESUMED = "esmda"


def hmflow(*args: str, cwd: Path, api: str, timeout: int = 900) -> subprocess.CompletedProcess:
    env = cli_env(api, COLUMNS="200")
    return subprocess.run([sys.executable, "-m", "hmflow.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


@pytest.mark.parametrize("methods", [
    pytest.param(METHODS, id="two-kinds"),
    pytest.param(tuple(AGENTS), id="every-method", marks=pytest.mark.slow)])
def test_bench_runs_every_method_and_seed_with_exactly_the_budgeted_calls(tmp_path, methods,
                                                                         small_case, prefect_api):
    common = ["bench", "--case", str(small_case), "--budget", str(BUDGET), "--workers", "2",
              "--storage", str(tmp_path / "store"), "--name", "b"]
    run = hmflow(*common, "--seeds", str(SEEDS), "--methods", ",".join(methods), cwd=tmp_path,
                 api=prefect_api)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    version = sorted((tmp_path / "store" / "b" / "benchmark").glob("v*"))[-1]
    calls = pd.read_parquet(version / "calls.parquet")
    # every method x seed, each with exactly the budget: LM's Jacobian runs and ES-MDA's
    # ensemble members are calls like any other
    counts = calls.groupby(["method", "seed"]).size()
    assert set(counts.index) == {(m, s) for m in methods for s in range(SEEDS)}
    assert (counts == BUDGET).all(), counts.to_dict()
    assert set(calls[calls.method == "lm"].phase) >= {"jacobian"}
    assert set(calls[calls.method == "esmda"].phase) >= {"ensemble", "posterior"}
    # each campaign's journal holds the same calls as the table
    names = {ms: c for c, ms in bench_names("synthetic", list(methods), list(range(SEEDS)),
                                            "b")[2].items()}
    for (method, seed), n in counts.items():
        journal = tmp_path / "store" / names[(method, seed)] / "evaluations"
        assert len(list(journal.glob("*.json"))) == n
    table = pd.read_parquet(version / "summary.parquet")
    assert sorted(table.method) == sorted(methods) and (table.seeds == SEEDS).all()
    text = (version / "summary.md").read_text()
    assert all(f"| {m} |" in text for m in methods) and "floor E" in text
    png = (version / "best_so_far.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    # the best-so-far column never picks a failed or penalised call
    for _, g in calls.groupby(["method", "seed"]):
        valid = g.E.where(g.status == "COMPLETE").to_numpy()
        expected = [np.nanmin(valid[: k + 1]) if np.isfinite(valid[: k + 1]).any() else np.nan
                    for k in range(len(valid))]
        np.testing.assert_allclose(g.best.to_numpy(), expected)
    assert "| method |" in run.stdout

    # the worst well's C_match of every scored call, and at each run's best call
    scored = calls.status != "FAIL"
    assert calls[scored].worst_well_cmatch.between(0, 100).all()
    assert table.worst_well_cmatch_median.notna().any()

    # exported (benchmarks/export_bench.py) and unpacked into another store, as on another
    # machine, the same command with one more seed continues it: the done campaign is
    # replayed (nothing simulated, nothing rewritten, the same rows), only the new seed runs
    # (a method added later is another campaign the same way: -m slow's every-method run)
    export = subprocess.run([sys.executable, str(Path(__file__).resolve().parents[1] / "benchmarks"
                                                 / "export_bench.py"), "--name", "b", "--storage",
                             str(tmp_path / "store"), "--out", str(tmp_path / "out")],
                            capture_output=True, text=True, timeout=300, check=False)
    assert export.returncode == 0, export.stderr[-3000:]
    other = tmp_path / "other-machine" / "store"
    other.mkdir(parents=True)
    with tarfile.open(tmp_path / "out" / "b" / "journals.tar.gz") as tar:
        tar.extractall(other, filter="data")
    bound = json.loads((other / "b" / "campaign.json").read_text())["case_artifact"]
    case = ArtifactStore(other).get(bound["campaign"], bound["step"], bound["version"])
    assert case.verify() == []  # the case the benchmark is bound to came along, intact
    done = other / names[(RESUMED, 0)]
    before = {p: p.stat().st_mtime_ns for p in done.glob("evaluations/*")}
    moved = hmflow(*common[:-4], "--storage", str(other), "--name", "b", "--methods",
                   RESUMED, "--seeds", str(SEEDS + 1), cwd=tmp_path / "other-machine",
                   api=prefect_api)
    assert moved.returncode == 0, moved.stdout[-3000:] + moved.stderr[-3000:]
    assert before and {p: p.stat().st_mtime_ns for p in before} == before  # nothing rewritten
    assert not (done / "runs").exists()  # no simulator call: that campaign was complete
    there = pd.read_parquet(max((other / "b" / "benchmark").glob("v*")) / "calls.parquet")
    assert set(there.method) == {RESUMED} and set(there.seed) == set(range(SEEDS + 1))
    assert (there.groupby(["method", "seed"]).size() == BUDGET).all()
    key = ["method", "seed", "call", "E"]
    pd.testing.assert_frame_equal(
        there[there.seed == 0][key].sort_values("call").reset_index(drop=True),
        calls[calls.method == RESUMED][key].sort_values("call").reset_index(drop=True))
    folder = other / next(iter(bench_names("synthetic", [RESUMED], [1], "b")[2]))
    assert json.loads((folder / "campaign.json").read_text())["seed"] == 1
    records = [json.loads(p.read_text()) for p in (folder / "evaluations").glob("*.json")]
    assert any(r.get("E_worst") is not None and r["E_worst"] >= 0 for r in records)


def test_summary_counts_levels_and_gap_from_the_calls():
    """Hand-made calls: levels reached, the gap closed and a seed that never gets there."""
    floor, centre = 1.0, 3.0
    rows = []
    for seed, es in enumerate([[2.0, 1.4, 1.15, 1.05], [2.5, 1.45, "FAIL", 1.6]]):
        for call, e in enumerate(es, start=1):
            failed = e == "FAIL"
            rows.append({"method": "m", "seed": seed, "call": call,
                         "status": "FAIL" if failed else "COMPLETE",
                         "E": np.nan if failed else e, "penalty": 0.0, "wall_time_s": 1.0,
                         "sim_time_s": 1.0, "finished_at": 100.0 + call})
    runs = per_run(pd.DataFrame(rows), floor, centre)
    first = runs[runs.seed == 0].iloc[0]
    assert [first[f"calls_to_{lv:g}x"] for lv in LEVELS] == [2.0, 3.0, 4.0]
    second = runs[runs.seed == 1].iloc[0]
    assert second["calls_to_1.5x"] == 2.0 and np.isinf(second["calls_to_1.2x"])
    assert second["failed"] == 1 and second["best_E"] == 1.45  # carried over the failed call
    table = summary(runs).iloc[0]
    assert table["reached_1.1x"] == 1 and np.isinf(table["calls_to_1.1x"])  # median of 4, inf
    assert table["calls_to_1.5x"] == 2.0 and table["reached_1.5x"] == 2
    assert np.isnan(first["gap_closed_25"])  # fewer calls than the mark: no value


def test_speedup_pairs_the_same_campaigns_of_two_benchmarks():
    """1 worker and 2 workers, the same method and seed: the speed-up is the wall-time ratio;
    a campaign only one benchmark ran has no row."""
    from hmcore.reporting.benchmark import speedup

    def runs(workers: int, seeds: list[int]) -> pd.DataFrame:
        rows = []
        for seed in seeds:
            for call in range(1, 5):  # 4 calls of 10 s, W at a time, 1 s apart
                start = 1000.0 + (call - 1) // workers * 11.0
                rows.append({"method": "m", "seed": seed, "call": call, "status": "COMPLETE",
                             "E": 2.0 / call, "penalty": 0.0, "wall_time_s": 10.0,
                             "sim_time_s": 9.0 + 0.5 * workers, "finished_at": start + 10.0})
        return per_run(pd.DataFrame(rows), 1.0, 3.0, workers)

    table = speedup(runs(1, [0, 1]), runs(2, [0]))
    assert table[["method", "seed"]].values.tolist() == [["m", 0]]
    row = table.iloc[0]
    assert row["wall_min_1"] * 60 == pytest.approx(43.0) and row["wall_min_w"] * 60 == pytest.approx(21.0)
    assert row["speedup"] == pytest.approx(43.0 / 21.0)
    assert row["sim_s_per_call_1"] == pytest.approx(9.5) and row["sim_s_per_call_w"] == pytest.approx(10.0)
    assert (row["calls_1"], row["calls_w"]) == (4, 4)
    # overhead: wall time over the simulator time per worker, less 1
    assert row["overhead_1"] == pytest.approx(43.0 / 38.0 - 1)
    assert row["overhead_w"] == pytest.approx(21.0 / 20.0 - 1)
