"""Plain-JSON conversion of Python, NumPy and pandas values, and canonical-JSON hashing.

The one JSON encoder of hmflow: the store, the journal, the reports and the diagnosis all
write through :func:`to_jsonable`. Non-finite floats (``NaN``, ``+inf``, ``-inf``) are stored
as ``null``: JSON has no spelling for them. They read back as ``None`` (``NaN`` once loaded
into a numeric DataFrame column), so a stored ``inf`` does not come back as ``inf``.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from datetime import date, datetime
from enum import Enum
from pathlib import PurePath
from typing import Any

import numpy as np
import pandas as pd

SUPPORTED = ("None, bool, int, float, str, enums (their value), list, tuple, dict with str "
             "keys, numpy scalars and arrays, datetime/date, pathlib paths")


def to_jsonable(value: Any, where: str = "value") -> Any:
    """Return ``value`` as plain JSON data (dict, list, str, int, float, bool, None).

    NumPy scalars and arrays become Python values and lists, tuples become lists, enums their
    value, datetimes become ISO strings, paths become strings, and NaN/inf/NaT/pd.NA become
    ``None``.
    ``where`` names the value in error messages. Raises TypeError for anything else (sets
    included: they have no order) and for dict keys that are not strings.
    """
    if value is None or value is pd.NA or value is pd.NaT:
        return None
    if isinstance(value, Enum):  # before str: a str-valued enum is a str too
        return to_jsonable(value.value, where)
    if isinstance(value, bool):
        return value
    if isinstance(value, str):
        return str(value)
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.datetime64):
        return None if np.isnat(value) else pd.Timestamp(value).isoformat()
    if isinstance(value, np.generic):
        return to_jsonable(value.item(), where)
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist(), where)
    if isinstance(value, Mapping):
        out = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise TypeError(f"{where}: dict keys must be strings, got {key!r} "
                                f"({type(key).__name__})")
            out[str(key)] = to_jsonable(item, f"{where}[{key!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [to_jsonable(item, f"{where}[{i}]") for i, item in enumerate(value)]
    if isinstance(value, (datetime, date)):
        return value.isoformat()
    if isinstance(value, PurePath):
        return str(value)
    raise TypeError(f"{where}: cannot store {type(value).__name__} as JSON "
                    f"(supported: {SUPPORTED})")


def canonical_json(value: Any) -> str:
    """Canonical JSON text of ``value`` (via :func:`to_jsonable`): sorted keys, no spaces."""
    return json.dumps(to_jsonable(value), sort_keys=True, separators=(",", ":"),
                      ensure_ascii=False, allow_nan=False)


def sha256_json(value: Any) -> str:
    """Hex sha256 of the UTF-8 canonical JSON of ``value``."""
    return hashlib.sha256(canonical_json(value).encode("utf-8")).hexdigest()
