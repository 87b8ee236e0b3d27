"""What identifies a case's inputs: SHA-256 hashes of its case file, of every file its deck
reads and of its history (stored with the case as run, compared to know the same case)."""

from __future__ import annotations

import hashlib
from pathlib import Path

from hmcore.eclipse.includes import deck_files
from hmcore.model.case import Case


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, in hex."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def deck_file_hashes(case: Case) -> dict[str, str]:
    """SHA-256 of every file the deck reads (the main file and its INCLUDEs, recursively,
    wherever they are); other files beside the deck do not count. Keyed by the path relative
    to the deck's folder (so the case folder can move), absolute for a file outside it."""
    home = Path(case.deck).resolve().parent

    def key(p: Path) -> str:
        return str(p.relative_to(home)) if p.is_relative_to(home) else str(p)

    return {key(p): file_sha256(p) for p in deck_files(case.deck)}


def case_fingerprint(case: Case) -> dict:
    """What identifies a case's inputs: hashes of the case file, every file the deck reads,
    and the history."""
    return {"case_file": file_sha256(case.source), "deck": file_sha256(case.deck),
            "deck_files": deck_file_hashes(case), "observed": file_sha256(case.observed_path)}
