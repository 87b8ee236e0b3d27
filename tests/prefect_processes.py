"""Real Prefect processes for the tests: a `prefect server start` on a free loopback port with
its own temporary PREFECT_HOME, a `prefect worker start`, and their stop (SIGTERM to the process
and every child, then SIGKILL). conftest.prefect_server holds the session's one server."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import psutil
import pytest

PREFECT = Path(sys.executable).with_name("prefect")
SERVER_STARTUP_S = 120


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def isolated_env(home: Path, api_url: str, **extra: str) -> dict[str, str]:
    """This environment without any PREFECT_* variable, plus a temporary PREFECT_HOME (its own
    profiles and database) and our server's API URL."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update({"PREFECT_HOME": str(home), "PREFECT_API_URL": api_url,
                "PREFECT_SERVER_ANALYTICS_ENABLED": "false", **extra})
    return env


def start_process(cmd: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    out = open(log, "wb")
    try:
        return subprocess.Popen(cmd, env=env, cwd=str(log.parent), stdin=subprocess.DEVNULL,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    finally:
        out.close()  # the child keeps its own descriptor


def stop_process(proc: subprocess.Popen, grace_s: float = 15.0) -> None:
    """SIGTERM the process and everything it started (by pid, collected first), then SIGKILL
    whatever is still alive after ``grace_s``."""
    try:
        family = [psutil.Process(proc.pid)]
        family += family[0].children(recursive=True)
    except psutil.NoSuchProcess:
        family = []
    for p in family:
        try:
            p.send_signal(signal.SIGTERM)
        except psutil.NoSuchProcess:
            pass
    _, alive = psutil.wait_procs(family, timeout=grace_s)
    for p in alive:
        try:
            p.kill()
        except psutil.NoSuchProcess:
            pass
    psutil.wait_procs(alive, timeout=5)
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:  # pragma: no cover - killed above
        pass


def tail(path: Path, n: int = 4000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return "(no log)"


@contextlib.contextmanager
def serve_prefect(root: Path, ui: bool = False):
    """A real `prefect server start` on a free loopback port with a temporary PREFECT_HOME under
    ``root`` (with its web UI when ``ui``); yields its API URL, home, env, root and log."""
    home = root / "home"
    home.mkdir()
    port = free_port()
    api = f"http://127.0.0.1:{port}/api"
    env = isolated_env(home, api)
    log = root / "server.log"
    cmd = [str(PREFECT), "server", "start", "--host", "127.0.0.1", "--port", str(port)]
    proc = start_process(cmd + ([] if ui else ["--no-ui"]), env, log)
    try:
        deadline = time.monotonic() + SERVER_STARTUP_S
        while True:
            if proc.poll() is not None:
                pytest.fail(f"prefect server exited with {proc.returncode}:\n{tail(log)}")
            try:
                with urllib.request.urlopen(f"{api}/health", timeout=2) as r:
                    if r.status == 200 and json.loads(r.read()) is True:
                        break
            except OSError:
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"prefect server not healthy after {SERVER_STARTUP_S} s:\n{tail(log)}")
            time.sleep(0.5)
        yield {"api": api, "ui": api[: -len("/api")], "home": home, "env": env, "root": root,
               "log": log}
    finally:
        stop_process(proc)


@contextlib.contextmanager
def serve_worker(server: dict, pool: str, name: str):
    """A real `prefect worker start --pool POOL` subprocess (polling every 2 s), stopped before
    the server fixture stops the server: a worker without its server keeps retrying."""
    log = server["root"] / f"{name}.log"
    env = dict(server["env"], PREFECT_WORKER_QUERY_SECONDS="2")
    proc = start_process([str(PREFECT), "worker", "start", "--pool", pool, "--name", name,
                          "--limit", "1"], env, log)
    try:
        yield {"proc": proc, "log": log}
    finally:
        stop_process(proc)
