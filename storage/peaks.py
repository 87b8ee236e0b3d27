"""The highest peak memory the store has measured for runs of one deck (checked against a
batch job's memory before any job is submitted: ``hmcore.model.cluster.cluster_problems``).

A deck is known by the hashes of every file it reads (``deck_files`` in the inputs of a
campaign's ``case`` artifact, :func:`hmcore.model.fingerprint.deck_file_hashes`); its runs
are the records of every journal of every campaign made from it (calibration calls, a
diagnosis's runs, an ensemble's members), each with the simulator's ``peak_rss_bytes``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from .journal import EvaluationJournal
from .store import JOURNAL_STEP, ArtifactStore, is_journal_folder

CASE_STEP = "case"


@dataclass(frozen=True)
class MeasuredPeak:
    """The highest measured peak (bytes), the campaign and journal index of the run that
    reached it, and how many runs of the deck were measured."""

    bytes: float
    campaign: str
    index: int
    runs: int


def measured_peak(store: ArtifactStore, deck_files: Mapping[str, str]) -> MeasuredPeak | None:
    """The highest ``peak_rss_bytes`` over the runs of the deck whose file hashes are
    ``deck_files`` in every campaign of ``store``; None when no run of it was measured (a new
    deck or store, or runs that ended before they were read). A campaign whose case artifact
    cannot be read is skipped."""
    best: MeasuredPeak | None = None
    runs = 0
    if not store.root.is_dir():
        return None
    for campaign in store.campaigns():
        try:
            case = store.latest(campaign, CASE_STEP)
        except (OSError, ValueError):
            continue
        if case is None or (case.manifest.get("inputs") or {}).get("deck_files") != dict(
                deck_files):
            continue
        try:
            rows = [row for folder in _journal_folders(store, campaign)
                    for row in EvaluationJournal(store, campaign, _journal_name(folder)).rows()]
        except (OSError, ValueError):  # removed or rewritten meanwhile: not this deck's word
            continue
        for row in rows:
            peak = row.get("peak_rss_bytes")
            if not isinstance(peak, (int, float)) or not math.isfinite(peak) or peak <= 0:
                continue
            runs += 1
            if best is None or peak > best.bytes:
                best = MeasuredPeak(float(peak), campaign, int(row["index"]), 0)
    return None if best is None else MeasuredPeak(best.bytes, best.campaign, best.index, runs)


def _journal_folders(store: ArtifactStore, campaign: str) -> list[str]:
    directory = store.root / campaign
    return sorted(p.name for p in directory.iterdir() if p.is_dir() and is_journal_folder(p.name))


def _journal_name(folder: str) -> str | None:
    return None if folder == JOURNAL_STEP else folder[len(JOURNAL_STEP) + 1:]
