"""The store's file system as a fault, not a simulation result: a store folder that went away
while a command runs, and a disk too full for a call's run to mean anything.

A simulator that finds no space for its output fails, and that failure says nothing about the
model: recording it as the call's result would lose the call (a resumed campaign never runs a
journaled call again). So a failed call on a store with less than :data:`MIN_FREE_BYTES` free
raises ``OSError(ENOSPC)`` instead of being journaled, and the call runs again when the same
command is run after space is freed.

:data:`FAULTS` and :func:`is_fault` tell a command which ``OSError`` is the store's file system
failing (to be said in one line with its fix) rather than a bug.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path
from typing import NamedTuple


class Fault(NamedTuple):
    """What a file system error means for the store, and what the user does about it."""

    what: str
    fix: str
    anywhere: bool  # a fault wherever it happens (else only on a path inside the store)


FAULTS = {
    errno.ENOSPC: Fault("no space left", "free space", True),
    errno.EDQUOT: Fault("disk quota exceeded", "free space (or raise the quota)", True),
    errno.EROFS: Fault("read-only file system",
                       "make the store writable (or give --storage on a writable disk)", True),
    errno.EACCES: Fault("permission denied",
                        "make the store writable for this user (or give another --storage)",
                        False),
    errno.EPERM: Fault("operation not permitted",
                       "make the store writable for this user (or give another --storage)",
                       False),
    errno.ENOENT: Fault("a folder of the store is not there (removed while running?)",
                        "restore or recreate the store's folder", False),
}
"""The file system errors a command reports as one line instead of a traceback."""


def is_fault(exc: BaseException, root: Path | str) -> bool:
    """Whether ``exc`` is the store at ``root`` failing (:data:`FAULTS`): a full or read-only
    file system anywhere, a missing or forbidden path only inside the store."""
    if not isinstance(exc, OSError) or exc.errno not in FAULTS:
        return False
    return FAULTS[exc.errno].anywhere or inside(exc.filename, root)


def inside(path: object, root: Path | str) -> bool:
    """Whether ``path`` (a file name an ``OSError`` carries) is ``root`` or below it."""
    if not isinstance(path, (str, os.PathLike)):
        return False
    try:
        Path(os.path.abspath(path)).relative_to(os.path.abspath(root))
    except ValueError:
        return False
    return True


MIN_FREE_BYTES = 1 << 20
"""Below this much free space on the store, a failed call is taken for a full disk."""


def require_store(root: Path | str) -> Path:
    """``root`` when it is a folder; ``FileNotFoundError`` naming it otherwise (the store was
    removed, or its file system unmounted, while a command ran: writing on would start a new,
    empty store under the same path)."""
    path = Path(root)
    if not path.is_dir():
        raise FileNotFoundError(errno.ENOENT, "the store's folder is not there (removed while "
                                "the command ran?)", str(path))
    return path


def full_disk(path: Path | str) -> OSError | None:
    """``OSError(ENOSPC)`` naming ``path`` when its file system has less than
    :data:`MIN_FREE_BYTES` free (or a missing folder's error), else None."""
    try:
        free = shutil.disk_usage(path).free
    except OSError as exc:
        return exc
    if free < MIN_FREE_BYTES:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return None
