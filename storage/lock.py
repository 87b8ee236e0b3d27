"""One process per name: an exclusive lock on a campaign's, benchmark's, diagnosis's or
ensemble's name in the store, taken before anything is simulated.

The lock is ``ROOT/.locks/<name>.json`` (a hidden folder: no listing of campaigns sees it),
holding the holder's host, pid, the pid's start time (``/proc/<pid>/stat``, in clock ticks
since boot, with the boot's id: a reused pid or a reboot is not the holder), when it was taken
and the command. It is written as the journal writes a record (a temp file, fsync'd, moved
into place) while ``ROOT/.locks/<name>.guard`` is held with ``flock``, so two processes that
both find the lock free or stale cannot both take it. The holder keeps the guard's descriptor
closed between takes: the lock file, not an open descriptor, is the lock, so that it outlives
nothing but its process and is readable on every host of a shared file system.

A lock whose holder is on this host and no longer runs (no such pid, or the pid started at
another time: reused) is stale and taken over with a warning; a lock held from another host is
respected (this host cannot see its processes). The same process taking its own lock again
(the CLI, then the flow it calls) gets a handle that does not release it.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import Enum
from pathlib import Path
from types import TracebackType
from typing import Self

from .store import validate_name

LOCKS = ".locks"
"""The folder of the locks, at the store's root (hidden: not a campaign)."""


class NameKind(str, Enum):
    """What holds a name in the store."""

    CAMPAIGN = "campaign"
    BENCHMARK = "benchmark"
    DIAGNOSIS = "diagnosis"
    ENSEMBLE = "ensemble"


class LockState(str, Enum):
    """What a lock file says about its holder, seen from this host."""

    FREE = "free"          # no lock file
    RUNNING = "running"    # held by a live process on this host
    REMOTE = "remote"      # held from another host: respected
    STALE = "stale"        # held by a process of this host that no longer runs
    OWN = "own"            # held by this very process


@dataclass(frozen=True)
class Holder:
    """Who holds a name: what the lock file says."""

    kind: NameKind
    name: str
    host: str
    pid: int
    start_ticks: int | None
    boot_id: str | None
    since: str
    command: str

    def describe(self) -> str:
        """``pid 123 on host h since 2026-11-28 16:40:03 UTC``."""
        try:
            since = datetime.fromisoformat(self.since).strftime("%Y-%m-%d %H:%M:%S UTC")
        except ValueError:
            since = self.since
        return f"pid {self.pid} on host {self.host} since {since}"


class NameHeldError(RuntimeError):
    """Another live process holds the name; ``holder`` says who. ``str()`` is one line with
    what to do."""

    def __init__(self, holder: Holder, path: Path):
        self.holder = holder
        self.path = path
        where = ("on this host" if holder.host == socket.gethostname()
                 else f"on {holder.host}, another host of this store")
        super().__init__(
            f"{holder.kind.value} '{holder.name}' is already running: {holder.describe()} "
            f"holds {path}; wait for it to end (or stop it: kill {holder.pid} {where}), or "
            f"choose another name. A lock whose process has died is taken over by itself")


def lock_path(root: Path | str, name: str) -> Path:
    """Where the lock of ``name`` lives in the store at ``root``."""
    return Path(root) / LOCKS / f"{validate_name('campaign', name)}.json"


def process_start(pid: int) -> int | None:
    """The start time of ``pid`` on this host, in clock ticks since boot; None if it does not
    run (or /proc cannot tell)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])  # field 22: starttime


def boot_id() -> str | None:
    """This boot's id (a pid's start time means nothing across a reboot)."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return None


def read_holder(path: Path) -> Holder | None:
    """The holder a lock file names; None when there is none. A lock file that cannot be read
    (truncated by a crash before this format's atomic write) is no holder."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return Holder(kind=NameKind(data["kind"]), name=str(data["name"]),
                      host=str(data["host"]), pid=int(data["pid"]),
                      start_ticks=data.get("start_ticks"), boot_id=data.get("boot_id"),
                      since=str(data.get("since", "")), command=str(data.get("command", "")))
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def state_of(holder: Holder | None) -> LockState:
    """What ``holder`` means from this process on this host."""
    if holder is None:
        return LockState.FREE
    if holder.host != socket.gethostname():
        return LockState.REMOTE
    if holder.boot_id and boot_id() and holder.boot_id != boot_id():
        return LockState.STALE
    started = process_start(holder.pid)
    if started is None or (holder.start_ticks is not None and started != holder.start_ticks):
        return LockState.STALE
    if holder.pid == os.getpid():
        return LockState.OWN
    return LockState.RUNNING


class NameLock:
    """The lock on one name; a context manager. ``acquire`` raises :class:`NameHeldError`
    when a live process (or another host) holds the name; ``taken_over`` is the stale holder
    it replaced (None otherwise), for the caller to warn about."""

    def __init__(self, root: Path | str, name: str, kind: NameKind):
        self.root = Path(root)
        self.name = validate_name("campaign", name)
        self.kind = NameKind(kind)
        self.path = lock_path(self.root, name)
        self.taken_over: Holder | None = None
        self._owned = False
        self._token = uuid.uuid4().hex

    def __repr__(self) -> str:
        return f"NameLock({str(self.path)!r}, {self.kind.value})"

    def acquire(self) -> NameLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with _guard(self.path):
            holder = read_holder(self.path)
            state = state_of(holder)
            if state in (LockState.RUNNING, LockState.REMOTE):
                raise NameHeldError(holder, self.path)
            if state is LockState.OWN:
                return self  # the CLI's lock, taken again by its flow: released by the CLI
            self.taken_over = holder if state is LockState.STALE else None
            data = {"kind": self.kind.value, "name": self.name, "host": socket.gethostname(),
                    "pid": os.getpid(), "start_ticks": process_start(os.getpid()),
                    "boot_id": boot_id(), "since": datetime.now(UTC).isoformat(),
                    "command": " ".join(sys.argv)[:500], "token": self._token}
            tmp = self.path.with_name(f".{self.path.name}.{self._token}.tmp")
            try:
                with open(tmp, "x", encoding="utf-8") as f:
                    f.write(json.dumps(data, indent=2) + "\n")
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, self.path)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
            self._owned = True
        return self

    def release(self) -> None:
        """Remove the lock if this handle took it (and it is still ours); never raises for a
        store that went away."""
        if not self._owned:
            return
        self._owned = False
        try:
            with _guard(self.path):
                data = json.loads(self.path.read_text(encoding="utf-8"))
                if data.get("token") == self._token:
                    self.path.unlink()
        except (OSError, ValueError):
            pass

    def __enter__(self) -> Self:
        return self.acquire()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.release()


class _guard:
    """``flock`` on ``<lock>.guard`` while a lock is read and written (held for milliseconds)."""

    def __init__(self, path: Path):
        self.path = path.with_name(path.stem + ".guard")
        self.fd = -1

    def __enter__(self) -> None:
        self.fd = os.open(self.path, os.O_CREAT | os.O_RDWR, 0o666)
        fcntl.flock(self.fd, fcntl.LOCK_EX)

    def __exit__(self, *exc: object) -> None:
        try:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        finally:
            os.close(self.fd)
