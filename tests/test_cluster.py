"""Simulator calls on workers in other processes, as on a cluster: a `dask scheduler` and two
`dask worker` processes started from the command line, `hmflow run --task-runner dask
--dask-address ...` (real OPM Flow, real Prefect, real store); then the same with one worker
killed (its whole process group, as when a machine goes away) in the middle of a call: the
call is rerun on the other worker and the campaign ends with exactly the budgeted
evaluations, none lost, none twice. The small synthetic case (conftest.small_case) and the
session's Prefect server (conftest.prefect_api)."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest
from conftest import cli_env

DASK = Path(sys.executable).with_name("dask")
BUDGET = 4  # was 6 (issue 40, suite time): the kill lands at the 3rd call, with calls left

pytestmark = [pytest.mark.opm,
              pytest.mark.skipif(not DASK.exists(), reason="the dask command is not installed")]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(args: list[str], log: Path, cwd: Path) -> subprocess.Popen:
    """A process in its own process group (killed as a whole, as a lost machine is)."""
    return subprocess.Popen(args, stdout=log.open("w"), stderr=subprocess.STDOUT, cwd=cwd,
                            start_new_session=True)


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(timeout=30)


@contextmanager
def dask_cluster(root: Path, workers: int = 2):
    """`dask scheduler` + ``workers`` x `dask worker` (1 process, 1 thread each), loopback."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [_start([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                     "--dashboard-address", "127.0.0.1:0"], root / "scheduler.log", root)]
    workers_ = []
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.5)
        for k in range(workers):
            (root / f"w{k}").mkdir(exist_ok=True)
            workers_.append(_start([str(DASK), "worker", address, "--nworkers", "1",
                                    "--nthreads", "1", "--name", f"w{k}",
                                    "--local-directory", str(root / f"w{k}")],
                                   root / f"worker{k}.log", root))
        import distributed

        with distributed.Client(address, timeout=60) as client:
            client.wait_for_workers(workers, timeout=120)
        yield {"address": address, "workers": workers_}
    finally:
        for p in workers_ + procs:
            _kill_group(p)


def _run(root: Path, address: str, campaign: str, case: Path, api: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "hmflow.cli", "run", "--case", str(case), "--agent", "random",
         "--budget", str(BUDGET), "--workers", "2", "--seed", "3", "--campaign", campaign,
         "--storage", str(root / "store"), "--task-runner", "dask", "--dask-address", address],
        cwd=root, env=cli_env(api), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _records(root: Path, campaign: str) -> list[dict]:
    return [json.loads(p.read_text())
            for p in sorted((root / "store" / campaign / "evaluations").glob("*.json"))]


def _worker_pids(address: str) -> dict[str, int]:
    import distributed

    with distributed.Client(address, timeout=30) as client:
        return {k: v for k, v in client.run(os.getpid).items()}


def _worker_running(workers: list[subprocess.Popen], run_dirs: list[Path]
                    ) -> subprocess.Popen | None:
    """The worker (its `dask worker` process) whose process tree runs a simulation in one of
    ``run_dirs``: the simulator's command line names its run directory; its parents lead to
    the worker. None while no such simulation is running."""
    by_pid = {w.pid: w for w in workers}
    wanted = [str(d) for d in run_dirs]
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if not any(d in cmd for d in wanted):
            continue
        pid = int(proc.name)
        for _ in range(8):  # up the parent chain to a worker
            if pid in by_pid:
                return by_pid[pid]
            try:
                stat = (Path("/proc") / str(pid) / "stat").read_text()
            except OSError:
                break
            pid = int(stat.rsplit(")", 1)[1].split()[1])
            if pid <= 1:
                break
    return None


def test_a_campaign_on_two_dask_workers_survives_one_killed_mid_call(tmp_path, small_case,
                                                                     prefect_api):
    """One campaign shows both (one test since 2026-11-25, for CI's time): the calls run in the
    worker processes, and a worker killed mid-call loses and duplicates nothing."""
    with dask_cluster(tmp_path) as cluster:
        pids = _worker_pids(cluster["address"])
        run = _run(tmp_path, cluster["address"], "killed", small_case, prefect_api)
        runs = tmp_path / "store" / "killed" / "runs"
        victim, killed_at = None, None
        deadline = time.time() + 600
        while time.time() < deadline and victim is None:  # the 3rd call has started
            started = sorted(p.name for p in runs.iterdir()) if runs.is_dir() else []
            if any(re.fullmatch(r"00000[2-3]", n) for n in started):
                busy = {r["index"] for r in _records(tmp_path, "killed")}
                running = [n for n in started if int(n[:6]) not in busy]
                # the worker whose simulator runs that call (calls go to whichever worker
                # frees first, so worker 0 may be idle at that moment)
                owner = _worker_running(cluster["workers"], [runs / n for n in running])
                if owner is not None:
                    victim, killed_at = owner, running
                    _kill_group(victim)
            time.sleep(0.2)
        assert victim is not None, "no call was seen running"
        out, _ = run.communicate(timeout=900)
    assert run.returncode == 0, out[-4000:]
    rows = _records(tmp_path, "killed")
    assert [r["index"] for r in rows] == list(range(BUDGET)), [r["index"] for r in rows]
    assert all(r["status"] in ("COMPLETE", "INVALID") for r in rows), rows
    assert all(Path(r["run_dir"]).is_dir() for r in rows)
    # each simulation ran in a worker process, not in hmflow's (the simulator's parent pid):
    # the first two calls ran at once, one on each worker
    ran_in = {r.get("host_pid") for r in rows}
    assert ran_in <= set(pids.values()) and len(ran_in) == 2, (ran_in, pids)
    # the killed call was run again (a fresh directory beside the one the dead worker left)
    reruns = [p.name for p in runs.iterdir() if "." in p.name]
    assert reruns, (sorted(p.name for p in runs.iterdir()), killed_at)
