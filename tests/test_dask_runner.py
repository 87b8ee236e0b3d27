"""Dask workers import hmflow's own packages (the campaign on a Dask cluster started from the
command line, and a worker killed mid-call, are in tests/test_cluster.py).

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

import pytest

requires_dask = pytest.mark.skipif(importlib.util.find_spec("prefect_dask") is None,
                                   reason="prefect-dask is not installed")

# loopback only; the scheduler's HTTP server on a free port rather than 8787
LOOPBACK = {"host": "127.0.0.1", "dashboard_address": "127.0.0.1:0"}


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
