"""The code version recorded in manifests: hmflow's installed version plus the git commit."""

from __future__ import annotations

import functools
import re
import subprocess
from importlib import metadata
from pathlib import Path

GIT_TIMEOUT_S = 5.0


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """``"<hmflow version>+git.<commit>"``; a part that cannot be found reads ``unknown``.

    The version is that of the installed ``hmflow`` distribution; the commit is ``HEAD`` of the
    git repository holding this file (uncommitted edits are not reflected). Returns
    ``"unknown"`` when neither is available. Cached: the code loaded in a process does not
    change when the repository moves on.
    """
    try:
        version = metadata.version("hmflow")
    except metadata.PackageNotFoundError:
        version = "unknown"
    commit = _git_commit() or "unknown"
    if version == commit == "unknown":
        return "unknown"
    return f"{version}+git.{commit}"


def _git_commit() -> str | None:
    try:
        done = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent,
                              check=True, timeout=GIT_TIMEOUT_S, capture_output=True, text=True)
    except (OSError, subprocess.SubprocessError):
        return None
    commit = done.stdout.strip()
    return commit if re.fullmatch(r"[0-9a-f]{40}|[0-9a-f]{64}", commit) else None
