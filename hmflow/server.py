"""The temporary Prefect server of a command run without ``PREFECT_API_URL``, as a child that
cannot outlive hmflow.

Prefect starts its own temporary server when no API is configured; that process survived a
``kill -9`` of hmflow (6 of 6 tries) and held its port and SQLite file. hmflow starts the same
server itself (Prefect's own uvicorn command and settings), with Linux's
``PR_SET_PDEATHSIG``: the kernel kills it the moment hmflow dies, however it dies. The server
runs in a session of its own: a signal to hmflow's process group (Ctrl-C in a terminal, a batch
system's SIGTERM to the job's processes, ``kill -- -PGID``) reaches hmflow alone, which records
its stop through the server and then stops it; in hmflow's group the server died first and
hmflow retried the dead API for minutes before it could exit. It points
``PREFECT_API_URL`` at it for the command and stops it when the command ends. A user who
configured a server (``PREFECT_API_URL``) gets that one, untouched.
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

STARTUP_TIMEOUT_S = 90.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


@contextlib.contextmanager
def temporary_api() -> Iterator[str | None]:
    """Yield the API URL the command uses: the configured one (nothing started), or a
    temporary server's, started here and stopped on exit (killed with hmflow if it dies)."""
    if os.environ.get("PREFECT_API_URL") or sys.platform != "linux":
        yield os.environ.get("PREFECT_API_URL")  # elsewhere: Prefect's own temporary server
        return
    # Prefect's own command, without importing Prefect (it reads its settings once, on import)
    app_dir = Path(importlib.util.find_spec("prefect").origin).parent.parent
    port = _free_port()
    url = f"http://127.0.0.1:{port}/api"
    env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
           "PREFECT__SERVER_FINAL": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "--app-dir", str(app_dir),
         "--factory", "prefect.server.api.server:create_app", "--host", "127.0.0.1",
         "--port", str(port), "--log-level", "error", "--lifespan", "on"],
        env=env, preexec_fn=_die_with_parent, start_new_session=True)
    try:
        wait_until_healthy(proc, url, STARTUP_TIMEOUT_S)
        os.environ["PREFECT_API_URL"] = url
        yield url
    finally:
        if os.environ.get("PREFECT_API_URL") == url:
            del os.environ["PREFECT_API_URL"]
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def wait_until_healthy(proc: subprocess.Popen, url: str, timeout_s: float) -> None:
    """Poll the API at ``url`` (``.../api``) until its health answers 200; raise
    ``RuntimeError`` if the server ``proc`` exits or ``timeout_s`` passes. One client for every
    poll: a client per poll (``httpx.get``) built a TLS context each time, about 0.1 s of CPU,
    50 times per start, on the core the server starts on."""
    import httpx  # only when a server is started: keeps `hmflow --help` fast

    deadline = time.monotonic() + timeout_s
    with httpx.Client(timeout=2) as client:
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"the Prefect server at {url} exited with code "
                                   f"{proc.returncode} while starting")
            try:
                if client.get(f"{url}/health").status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the Prefect server did not answer on {url} "
                                   f"within {timeout_s:g} s")
            time.sleep(0.2)
