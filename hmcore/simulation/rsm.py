"""Read an Eclipse RSM file: the text summary a simulator writes with ``RUNSUM``/``SEPARATE``
and production databases export.

An RSM file is a series of pages. Each page starts with a line ``1`` (form feed), a dashed
line, a title, a dashed line, then header lines in 13-character columns - vector names
(``TIME``, ``WOPR``...), units (``SM3/DAY``), multipliers (``*10**3``; OPM Flow leaves the
line out when no column has one), well or group names, and numbers (cells, regions) - a
dashed line and the rows. Every page repeats the time column
(``TIME`` in days, or ``DATE`` as ``1-JAN-1967``). Header cells are read by position (they may
be blank); rows are split on white space (no cell of a row is blank).

Errors name the file and the line, and all are reported at once.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from hmcore.errors import CaseError, Problem

WIDTH = 13
TIME_COLUMNS = ("TIME", "DATE", "DAYS")
_MULTIPLIER = re.compile(r"^\*10\*\*(-?\d+)$")
_DASHES = re.compile(r"^\s*-{10,}\s*$")
_FIX = ("export the summary as RSM (Eclipse RUNSUM / SEPARATE layout: names, units, "
        "multipliers, wells, numbers, then the rows), or give a .SMSPEC or an observed CSV")


@dataclass(frozen=True)
class RsmSummary:
    """The vectors of an RSM file: ``values['WOPR:PRO-1']`` over ``days`` (after START)."""

    path: Path
    days: np.ndarray
    values: dict[str, np.ndarray] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)

    def keys(self) -> list[str]:
        return list(self.values)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.values[key]


@dataclass
class _Page:
    line: int                  # 1-based line of the names row
    names: list[str]
    units: list[str]
    scales: list[float]
    wells: list[str]
    rows: list[tuple[int, list[str]]] = field(default_factory=list)


def _cells(line: str, n: int, offset: int = 1) -> list[str]:
    """The first ``n`` 13-character header cells of ``line``, from column ``offset`` (the
    names line's: 1 after Eclipse's leading space)."""
    body = line[offset:]
    return [body[i * WIDTH:(i + 1) * WIDTH].strip() for i in range(n)]


def _multipliers_and_wells(rest: list[list[str]], n: int) -> tuple[list[str], list[str]]:
    """The header lines after names and units: multipliers, wells, numbers - the multiplier
    line may be left out when no column has one (OPM Flow does)."""
    blank = [""] * n
    if len(rest) >= 3:
        return rest[0], rest[1]
    if rest and any(rest[0]) and all(_MULTIPLIER.match(c.replace(" ", "")) for c in rest[0] if c):
        return rest[0], rest[1] if len(rest) > 1 else blank
    return blank, rest[0] if rest else blank


def _pages(path: Path, lines: list[str], problems: list[Problem]) -> list[_Page]:
    pages: list[_Page] = []
    i = 0
    while i < len(lines):
        text = lines[i].strip()
        if text == "1" or _DASHES.match(lines[i]):
            # a page: [1], dashed, title, dashed, header lines (names first), dashed
            j = i + 1 if text == "1" else i
            if not (j + 3 < len(lines) and _DASHES.match(lines[j]) and _DASHES.match(lines[j + 2])):
                problems.append(Problem(f"{path}:{i + 1}", "a page does not start with the RSM "
                                        "header (dashed line, title, dashed line)", _FIX))
                return pages
            end = next((k for k in range(j + 4, min(j + 10, len(lines)))
                        if _DASHES.match(lines[k])), None)
            if end is None:
                problems.append(Problem(f"{path}:{j + 4}", "the header's closing dashed line "
                                        "is missing", _FIX))
                return pages
            header = lines[j + 3:end]
            n = len(header[0].split())
            offset = 1 if header[0].startswith(" ") else 0  # one offset for the whole page
            names = _cells(header[0], n, offset)
            if n == 0 or names != header[0].split():
                problems.append(Problem(f"{path}:{j + 4}", "the names line is not in "
                                        f"{WIDTH}-character columns", _FIX))
                return pages
            units = _cells(header[1], n, offset) if len(header) > 1 else [""] * n
            mults, wells = _multipliers_and_wells([_cells(h, n, offset) for h in header[2:]], n)
            scales = []
            for k, m in enumerate(mults):
                found = _MULTIPLIER.match(m.replace(" ", "")) if m else None
                if m and not found:
                    problems.append(Problem(f"{path}:{j + 6}", f"column {k + 1} ({names[k]}): "
                                            f"multiplier {m!r} is not *10**N", _FIX))
                scales.append(10.0 ** int(found.group(1)) if found else 1.0)
            pages.append(_Page(j + 4, names, units, scales, wells))
            i = end + 1
            continue
        if text and pages:
            pages[-1].rows.append((i + 1, lines[i].split()))
        elif text:
            problems.append(Problem(f"{path}:{i + 1}", "a data row before any header", _FIX))
            return pages
        i += 1
    return pages


def _time(page: _Page, cell: str, where: str, start: datetime | None,
          problems: list[Problem]) -> float | None:
    kind = page.names[0].upper()
    if kind == "DATE":
        if start is None:
            problems.append(Problem(where, "a DATE column needs the deck's START date", _FIX))
            return None
        for fmt in ("%d-%b-%Y", "%d-%B-%Y", "%Y-%m-%d"):  # never d/m/Y: US files read m/d/Y
            try:
                when = datetime.strptime(cell.replace("JLY", "JUL"), fmt)
                return (when - start).total_seconds() / 86400.0
            except ValueError:
                continue
        problems.append(Problem(where, f"DATE {cell!r} is not a date like 1-JAN-1967", _FIX))
        return None
    try:
        value = float(cell) * page.scales[0]
    except ValueError:
        problems.append(Problem(where, f"{page.names[0]} {cell!r} is not a number", _FIX))
        return None
    unit = page.units[0].strip().upper()
    if unit in ("", "DAYS", "DAY"):
        return value
    if unit in ("HOURS", "HOUR", "HRS", "HR"):  # a LAB deck's time
        return value / 24.0
    problems.append(Problem(where, f"{page.names[0]} in {page.units[0]!r}: expected DAYS or "
                            "HOURS", _FIX))
    return None


def read_rsm(path: Path, start: datetime | None = None) -> RsmSummary:
    """The vectors of RSM file ``path`` keyed ``NAME:WELL`` (``NAME`` for field vectors), in
    the file's units (``units[key]``) times its multipliers; ``start``: the deck's START, for
    a DATE column. CaseError listing every problem, with its line."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise CaseError([Problem(str(path), f"cannot read the RSM file: {exc}", _FIX)])
    problems: list[Problem] = []
    pages = _pages(path, lines, problems)
    if not pages and not problems:
        problems.append(Problem(str(path), "no RSM page found (no line '1' then a dashed "
                                "header)", _FIX))
    series: dict[str, dict[float, float]] = {}
    units: dict[str, str] = {}
    for page in pages:
        if page.names[0].upper() not in TIME_COLUMNS:
            problems.append(Problem(f"{path}:{page.line}", f"the first column is "
                                    f"{page.names[0]!r}; expected one of {list(TIME_COLUMNS)}",
                                    _FIX))
            continue
        keys = [f"{nm}:{w}" if w else nm for nm, w in zip(page.names, page.wells)]
        for line, cells in page.rows:
            where = f"{path}:{line}"
            if len(cells) != len(page.names):
                problems.append(Problem(where, f"{len(cells)} values for {len(page.names)} "
                                        f"columns ({', '.join(page.names)})", _FIX))
                continue
            day = _time(page, cells[0], where, start, problems)
            if day is None:
                continue
            for k in range(1, len(cells)):
                try:
                    value = float(cells[k].replace("D", "E")) * page.scales[k]
                except ValueError:
                    problems.append(Problem(where, f"column {k + 1} ({keys[k]}): {cells[k]!r} "
                                            "is not a number", _FIX))
                    continue
                series.setdefault(keys[k], {})[round(day, 6)] = value
                units[keys[k]] = page.units[k]
        if len(problems) > 50:
            break
    if not problems and not series:
        problems.append(Problem(str(path), "the RSM file holds no data row", _FIX))
    if problems:
        raise CaseError(problems[:50])
    days = np.array(sorted({d for s in series.values() for d in s}), dtype=float)
    values = {k: np.array([s.get(d, np.nan) for d in days], dtype=float)
              for k, s in series.items()}
    return RsmSummary(path, days, values, units)
