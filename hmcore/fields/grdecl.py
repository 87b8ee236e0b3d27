"""A member's fields as a GRDECL file (the INCLUDE a member's deck reads after its own grid
keywords), and GRDECL files read back.

Written: one keyword per field and per copy, a value for every cell of the grid (i fastest,
then j, then k), the active cells' values back from update space and truncated to the field's
bounds (:func:`hmcore.fields.transform.to_physical`), the inactive cells 0 (no pore volume,
no flow: an inactive cell stays inactive whatever OPM's MINPV). Runs of 4 or more equal
values are written ``N*v``; values have 7 significant digits (float32's precision).

Read: with OPM's own parser (``opm.io.Parser``), which knows every keyword, repeat counts
``N*v``, comments and the closing ``/``; its message is kept in a :class:`GrdeclError`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from opm.io.parser import ParseContext, Parser

from hmcore.eclipse.deck_info import quiet_stdout  # the one guard of fd 1 (OPM's chatter)
from hmcore.fields.grid import FieldGrid
from hmcore.fields.spec import FieldSpec
from hmcore.fields.transform import to_physical

PER_LINE = 6
MIN_RUN = 4
"""Runs of at least this many equal values are written as ``N*v``."""
INACTIVE_VALUE = 0.0


class GrdeclError(ValueError):
    """A GRDECL file OPM's parser refuses (its message), or that cannot be read."""


def member_arrays(fields: list[FieldSpec] | tuple[FieldSpec, ...],
                  values: Mapping[str, np.ndarray], grid: FieldGrid) -> dict[str, np.ndarray]:
    """{keyword: physical values of every cell ``(n_total,)``} of one member: ``values[name]``
    ``(n_active,)`` in update space per field, written to the field's keyword and copies."""
    out: dict[str, np.ndarray] = {}
    for f in fields:
        full = grid.full(to_physical(values[f.name], f), fill=INACTIVE_VALUE)
        for keyword in f.written:
            out[keyword] = full
    return out


def write_member(path: Path | str, fields: list[FieldSpec] | tuple[FieldSpec, ...],
                 values: Mapping[str, np.ndarray], grid: FieldGrid, header: str = "") -> Path:
    """Write one member's include (see :func:`member_arrays`) to ``path``; returns it."""
    return write_grdecl(path, member_arrays(fields, values, grid), header)


def write_grdecl(path: Path | str, arrays: Mapping[str, np.ndarray], header: str = "") -> Path:
    """Write ``{keyword: values}`` as GRDECL to ``path`` (through a temporary file and a
    rename, so that a reader never sees half a file); ``header`` lines become comments."""
    path = Path(path)
    parts = [f"-- {line}\n" for line in header.splitlines()]
    for keyword, values in arrays.items():
        values = np.asarray(values, dtype=np.float64).ravel()
        if not np.isfinite(values).all():
            raise ValueError(f"{keyword}: {int((~np.isfinite(values)).sum())} value(s) are "
                             "not finite")
        parts.append(f"{keyword}\n{format_values(values)}\n/\n\n")
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text("".join(parts), encoding="ascii")
    os.replace(tmp, path)
    return path


def format_values(values: np.ndarray) -> str:
    """GRDECL data of ``values`` ``(n,)``: :data:`PER_LINE` tokens a line, runs of
    :data:`MIN_RUN` or more equal values as ``N*v``."""
    if values.size == 0:
        return ""
    starts = np.flatnonzero(np.concatenate(([True], values[1:] != values[:-1])))
    lengths = np.diff(np.append(starts, values.size))
    tokens = []
    for start, length in zip(starts.tolist(), lengths.tolist()):
        text = f"{values[start]:.7g}"
        tokens.extend([f"{length}*{text}"] if length >= MIN_RUN else [text] * length)
    lines = (" ".join(tokens[i:i + PER_LINE]) for i in range(0, len(tokens), PER_LINE))
    return "\n".join(" " + line for line in lines)


def read_grdecl(path: Path | str) -> dict[str, np.ndarray]:
    """{keyword: values} of a GRDECL file (float64; integers for integer keywords such as
    ACTNUM), read by OPM's parser; GrdeclError with its message when it refuses the file."""
    path = Path(path)
    if not path.is_file():
        raise GrdeclError(f"{path}: no such file")
    try:
        with quiet_stdout():
            deck = Parser().parse(str(path), ParseContext())
    except (RuntimeError, ValueError) as exc:  # opm.io's, with the parser's text
        raise GrdeclError(" ".join(str(exc).split())) from exc
    out: dict[str, np.ndarray] = {}
    for keyword in deck:
        if len(keyword) == 0 or len(keyword[0]) == 0:  # no data: ECHO, NOECHO
            continue
        item = keyword[0][0]
        if item.is_double():
            out[keyword.name] = np.asarray(keyword.get_raw_array(), dtype=np.float64)
        elif item.is_int():  # ACTNUM, FIPNUM...
            out[keyword.name] = np.asarray(keyword.get_int_array(), dtype=np.int64)
    return out
