"""The campaign flow on prefect-dask's DaskTaskRunner with a real local Dask cluster (2 worker
processes, 1 thread each) and real OPM Flow runs, against a temporary Prefect server
(``prefect_test_harness``, SQLite in a temporary directory, temporary PREFECT_HOME).

A Dask worker puts its local directory first on ``sys.path`` and, with a memory limit (the
default), keeps its spill buffer in ``<local directory>/storage``: a namespace directory named
like hmflow's top-level ``storage`` package. With setuptools' default editable install (an
import hook consulted after the ordinary path search) that directory shadowed the package in
the worker, unpickling the ``simulate`` task failed and the flow waited forever. The Makefile
therefore installs in ``editable_mode=compat`` (the repository root on ``sys.path``, where a
regular package wins over a namespace directory); test_dask_worker_imports_the_project_storage_package
guards it with and without a memory limit.
"""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import pytest

PUNQ = Path(__file__).resolve().parents[2] / "shared" / "punqs3"
PUNQ_FILES = ("PUNQS3.DATA", "PUNQS3.GEO", "PUNQS3.PRP", "punqs3_observed_full_history.csv")
BUDGET = 4

_missing = [n for n in PUNQ_FILES if not (PUNQ / n).is_file()]
requires_punq = pytest.mark.skipif(
    bool(_missing), reason=f"PUNQ-S3 data not found in {PUNQ} (expected ../shared/punqs3 next "
                           f"to the repository; missing {_missing})")
requires_dask = pytest.mark.skipif(importlib.util.find_spec("prefect_dask") is None,
                                   reason="prefect-dask is not installed")

# loopback only; the scheduler's HTTP server on a free port rather than 8787
LOOPBACK = {"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"}
CLUSTER_KWARGS = {"n_workers": 2, "threads_per_worker": 1, "processes": True, **LOOPBACK}


def _recording_cluster_class():
    """A LocalCluster that, when the task runner closes it, notes which tasks its scheduler
    computed and on which worker processes (proof that the simulations ran on Dask)."""
    import distributed

    class RecordingCluster(distributed.LocalCluster):
        seen: list[dict] = []

        def close(self, *args, **kwargs):
            s = self.scheduler
            RecordingCluster.seen.append({
                "prefixes": {name: {"compute_s": dict(p.all_durations).get("compute", 0.0),
                                    "states": dict(p.state_counts)}
                             for name, p in s.task_prefixes.items()},
                "worker_pids": sorted(w.pid for w in s.workers.values()),
                "nthreads": sorted(w.nthreads for w in s.workers.values())})
            return super().close(*args, **kwargs)

    return RecordingCluster


def _write_case(tmp_path: Path) -> Path:
    path = tmp_path / "punqs3.toml"
    path.write_text(f'[case]\nname = "punqs3"\ndeck = "{PUNQ / "PUNQS3.DATA"}"\n'
                    f'observed = "{PUNQ / "punqs3_observed_full_history.csv"}"\n'
                    f"history_end_days = 2936\n")
    return path


@pytest.mark.opm
@requires_punq
@requires_dask
@pytest.mark.timeout(480)
def test_campaign_flow_on_a_local_dask_cluster(tmp_path):
    from prefect.settings import PREFECT_HOME, temporary_settings
    from prefect.testing.utilities import prefect_test_harness
    from prefect_dask import DaskTaskRunner

    from flows.campaign import campaign_flow
    from storage import ArtifactStore

    cluster_class = _recording_cluster_class()
    case = _write_case(tmp_path)
    storage = tmp_path / "store"
    home = tmp_path / "prefect-home"
    home.mkdir()
    runner = DaskTaskRunner(cluster_class=cluster_class, cluster_kwargs=dict(CLUSTER_KWARGS))
    with temporary_settings(updates={PREFECT_HOME: str(home)}):
        with prefect_test_harness(server_startup_timeout=120):
            result = campaign_flow.with_options(task_runner=runner)(
                case=str(case), agent="random", budget=BUDGET, workers=2, seed=1,
                storage=str(storage), campaign="punq-dask")

    assert result["campaign"] == "punq-dask" and result["storage"] == str(storage.resolve())
    rows = [json.loads(p.read_text())
            for p in sorted((storage / "punq-dask" / "evaluations").glob("*.json"))]
    assert [r["index"] for r in rows] == list(range(BUDGET))
    # every call simulated and scored (some may be penalised by a physics check, none failed)
    assert all(r["status"] in ("COMPLETE", "INVALID") for r in rows), [r.get("reason") for r in rows]
    store = ArtifactStore(storage)
    table = store.latest("punq-dask", "results").read_parquet("evaluations.parquet")
    assert len(table) == BUDGET and (table["status"] != "FAIL").all()
    assert store.latest("punq-dask", "best") is not None
    assert Path(result["report_path"]).is_file()

    # the simulations ran as Dask tasks on two worker processes, one thread each
    assert len(cluster_class.seen) == 1
    seen = cluster_class.seen[0]
    assert set(seen["prefixes"]) == {"simulate"}, seen
    assert seen["prefixes"]["simulate"]["states"].get("memory") == BUDGET, seen
    assert seen["prefixes"]["simulate"]["compute_s"] > 0
    assert len(seen["worker_pids"]) == 2 and os.getpid() not in seen["worker_pids"]
    assert seen["nthreads"] == [1, 1]


PROBE = """
import json, os, sys
import distributed

PACKAGE = sys.argv[2]

def probe():
    import importlib.util, os
    spec = importlib.util.find_spec(PACKAGE)
    return {"pid": os.getpid(), "origin": spec.origin if spec else None,
            "locations": list(spec.submodule_search_locations or []) if spec else []}

if __name__ == "__main__":
    kwargs = json.loads(sys.argv[1])
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  **kwargs) as cluster, distributed.Client(cluster) as client:
        print("PROBE " + json.dumps(client.submit(probe, pure=False).result(timeout=60)))
"""


@requires_dask
@pytest.mark.timeout(180)
@pytest.mark.parametrize("worker_kwargs", [
    pytest.param({"memory_limit": 0}, id="no-memory-limit"),
    pytest.param({}, id="default-memory-limit"),  # what `hmflow run --task-runner dask` uses
])
def test_dask_worker_imports_the_project_storage_package(worker_kwargs, tmp_path):
    """In a fresh interpreter whose sys.path does not hold the repository (as under the
    `hmflow` console script; `python -m pytest` run from the repository root puts it there and
    hides the problem), a Dask worker must import hmflow's own `storage` package."""
    import subprocess
    import sys

    from storage import ArtifactStore

    package = ArtifactStore.__module__.split(".")[0]  # "storage"
    expected = importlib.util.find_spec(package).origin
    script = tmp_path / "probe.py"
    script.write_text(PROBE)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, str(script), json.dumps({**LOOPBACK, **worker_kwargs}),
                           package],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=150)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PROBE ")]
    assert proc.returncode == 0 and lines, proc.stdout[-2000:] + proc.stderr[-4000:]
    probe = json.loads(lines[-1][len("PROBE "):])
    assert probe["origin"] == expected, probe
