"""One process per name (issue 43): the lock's rules on their own (storage.lock), without a
simulator: a live holder refuses a second taker, a dead or reused pid is stale, a lock from
another host is respected. With real `hmflow run` processes (tests/test_signals.py, on the
campaign it already kills and resumes): a lock left by a run killed with SIGKILL is taken
over by the same command, and a second process on a running campaign's name is refused at
once with the holder named while the first completes."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from storage.lock import (
    LockState,
    NameHeldError,
    NameKind,
    NameLock,
    lock_path,
    read_holder,
    state_of,
)


def _fake_lock(root: Path, name: str, **fields) -> Path:
    path = lock_path(root, name)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"kind": "campaign", "name": name, "host": socket.gethostname(), "pid": 1,
            "start_ticks": 1, "boot_id": None, "since": "2026-11-28T10:00:00+00:00",
            "command": "hmflow run", **fields}
    path.write_text(json.dumps(data))
    return path


def test_a_live_holder_refuses_a_second_taker_and_its_release_frees_the_name(tmp_path):
    child = subprocess.Popen([sys.executable, "-c",
                              ("import sys, time\n"
                              "from storage.lock import NameLock\n"
                              f"lock = NameLock({str(tmp_path)!r}, 'c1', 'campaign').acquire()\n"
                              "print('held', flush=True)\n"
                              "sys.stdin.read()\n"
                              "lock.release()\n")],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "held"
        with pytest.raises(NameHeldError) as refused:
            NameLock(tmp_path, "c1", NameKind.CAMPAIGN).acquire()
        assert refused.value.holder.pid == child.pid
        assert f"pid {child.pid} on host {socket.gethostname()}" in str(refused.value)
        assert "\n" not in str(refused.value)
        child.stdin.close()
        child.wait(timeout=30)
    finally:
        child.kill()
    assert not lock_path(tmp_path, "c1").exists()
    with NameLock(tmp_path, "c1", NameKind.CAMPAIGN) as lock:
        assert lock.taken_over is None
        assert read_holder(lock.path).pid == os.getpid()
        # the same process again (the CLI, then its flow): allowed, and it does not release
        with NameLock(tmp_path, "c1", NameKind.CAMPAIGN):
            pass
        assert lock.path.exists()
    assert not lock.path.exists()


def test_a_dead_or_reused_pid_is_stale_and_another_host_is_respected(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    _fake_lock(tmp_path, "gone", pid=dead.pid, start_ticks=None)
    assert state_of(read_holder(lock_path(tmp_path, "gone"))) is LockState.STALE
    # pid 1 runs, but it did not start at tick 1: a reused pid, not the holder
    _fake_lock(tmp_path, "reused", pid=1, start_ticks=1)
    assert state_of(read_holder(lock_path(tmp_path, "reused"))) is LockState.STALE
    with NameLock(tmp_path, "reused", NameKind.CAMPAIGN) as lock:
        assert lock.taken_over is not None and lock.taken_over.pid == 1
    _fake_lock(tmp_path, "remote", host="node-17.elsewhere", pid=os.getpid())
    with pytest.raises(NameHeldError, match="node-17.elsewhere, another host"):
        NameLock(tmp_path, "remote", NameKind.CAMPAIGN).acquire()
    assert read_holder(lock_path(tmp_path, "remote")).host == "node-17.elsewhere"
