"""Write-once evaluation journal: one JSON file per evaluation, written as it completes.

Records live in ``ROOT/<campaign>/evaluations/<index:06d>.json`` (a campaign's other journals,
e.g. a diagnosis's runs, in ``ROOT/<campaign>/evaluations-<name>/``). Each is written to a temp
file in the same folder, fsync'd and moved into place with ``os.replace``, so a killed campaign
leaves only whole records and can be resumed, and its report rebuilt, from :meth:`rows`.
Values go through :func:`storage.jsonable.to_jsonable`: NumPy scalars become Python numbers and
NaN/inf are stored as ``null`` (read back as ``None``, or ``NaN`` in :meth:`to_frame`).
"""

from __future__ import annotations

import json
import os
import re
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .jsonable import canonical_json, to_jsonable
from .store import ArtifactStore, journal_folder, refuse_links, validate_name

_RECORD_RE = re.compile(r"(\d{6,})\.json")


class JournalConflictError(ValueError):
    """An evaluation index is already recorded with different content (records are write-once)."""


class EvaluationJournal:
    """The evaluations of one campaign, one write-once JSON record per evaluation index;
    ``name``: another journal of the campaign (see :func:`storage.store.journal_folder`)."""

    def __init__(self, store: ArtifactStore, campaign: str, name: str | None = None):
        self.store = store
        self.campaign = validate_name("campaign", campaign)
        self.name = name
        self.folder = journal_folder(name)
        self.directory = store.root / campaign / self.folder

    def __repr__(self) -> str:
        named = "" if self.name is None else f", {self.name!r}"
        return f"EvaluationJournal({self.store!r}, {self.campaign!r}{named})"

    def path(self, index: int) -> Path:
        """Path of the record of evaluation ``index``."""
        return self.directory / f"{_check_index(index):06d}.json"

    def record(self, index: int, row: Mapping[str, Any]) -> Path:
        """Atomically write the record of evaluation ``index`` and return its path.

        The stored record is ``row`` plus ``"index": index`` (a row may carry ``index`` only
        if it is the same). Recording the same content again is a no-op; different content
        for a recorded index raises :class:`JournalConflictError`.
        """
        index = _check_index(index)
        if not isinstance(row, Mapping):
            raise TypeError(f"evaluation {index}: row must be a dict, got {type(row).__name__}")
        data = to_jsonable(row, f"evaluation {index}")
        given = data.get("index", index)
        if type(given) is not int or given != index:
            raise ValueError(f"evaluation {index}: the row's own 'index' is {given!r}")
        data["index"] = index
        target = self.path(index)
        if target.exists():
            existing = _read_record(target)
            if canonical_json(existing) == canonical_json(data):
                return target
            keys = sorted(k for k in existing.keys() | data.keys()
                          if canonical_json(existing.get(k)) != canonical_json(data.get(k))
                          or (k in existing) != (k in data))
            raise JournalConflictError(
                f"evaluation {index} is already recorded in {target} with different content "
                f"(differs in {keys}); records are write-once, use a new index")
        refuse_links(self.store.root, self.campaign, self.folder)
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.directory / f".tmp-{uuid.uuid4().hex}.part"  # never matches *.json
        try:
            with open(tmp, "x", encoding="utf-8") as f:
                f.write(json.dumps(data, sort_keys=True, ensure_ascii=False, allow_nan=False))
                f.write("\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, target)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        return target

    def get(self, index: int) -> dict[str, Any] | None:
        """The record of evaluation ``index``, or None when it is not recorded."""
        path = self.path(index)
        return _read_record(path) if path.exists() else None

    def indices(self) -> list[int]:
        """Recorded evaluation indices, ascending."""
        try:
            names = os.listdir(self.directory)
        except FileNotFoundError:
            return []
        return sorted(int(m.group(1)) for m in map(_RECORD_RE.fullmatch, names) if m)

    def rows(self) -> list[dict[str, Any]]:
        """All records, sorted by index; each includes its ``index``."""
        rows = []
        for index in self.indices():
            row = _read_record(self.path(index))
            if row.get("index") != index:
                raise ValueError(f"{self.path(index)}: record says index {row.get('index')!r}")
            rows.append(row)
        return rows

    def to_frame(self, flatten: bool = False) -> pd.DataFrame:
        """The records as a DataFrame, one row per evaluation, ``index`` as first column.

        Nested dicts (parameters, per-response losses...) stay dict cells unless ``flatten``,
        which spreads them into ``parent.child`` columns. Stored nulls become NaN in numeric
        columns (``None`` in object columns).
        """
        rows = self.rows()
        if not rows:
            return pd.DataFrame({"index": pd.Series([], dtype="int64")})
        frame = pd.json_normalize(rows, sep=".") if flatten else pd.DataFrame(rows)
        return frame[["index"] + [c for c in frame.columns if c != "index"]]


def _check_index(index: object) -> int:
    if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)) \
            or index < 0:
        raise ValueError(f"evaluation index must be an integer >= 0, got {index!r}")
    return int(index)


def _read_record(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise ValueError(f"{path}: unreadable evaluation record: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: evaluation record is not a JSON object")
    return data
