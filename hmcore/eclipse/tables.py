"""The Eclipse tables hmflow edits, column by column: how many columns a row has and which
of them a parameter may change. One home for these facts; :mod:`hmcore.model.parameters` checks a
parameter against them, :mod:`hmcore.model.run_deck` reshapes a table's numbers with them.

Columns are 1-based, as in the Eclipse manual: column 1 is the table's argument (a saturation,
a depth or a pressure) and is never edited.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class TableFamily(StrEnum):
    """What a table describes, and so which parameter kind edits it."""

    RELPERM = "relperm"  # saturation functions: relative permeabilities (kind ``relperm``)
    FLUID = "fluid"  # PVT and initial-state tables (kind ``table_multiply``)


@dataclass(frozen=True)
class TableLayout:
    """One table keyword: its family, the columns of a row, the columns a parameter edits."""

    keyword: str
    family: TableFamily
    width: int
    editable: tuple[int, ...]


TABLES: dict[str, TableLayout] = {t.keyword: t for t in (
    # saturation functions: a relative permeability in the editable columns; the last column
    # of SWOF / SGOF / SLGOF / SWFN / SGFN is the capillary pressure
    TableLayout("SWOF", TableFamily.RELPERM, 4, (2, 3)),
    TableLayout("SGOF", TableFamily.RELPERM, 4, (2, 3)),
    TableLayout("SWFN", TableFamily.RELPERM, 3, (2,)),
    TableLayout("SGFN", TableFamily.RELPERM, 3, (2,)),
    TableLayout("SOF3", TableFamily.RELPERM, 3, (2, 3)),
    TableLayout("SOF2", TableFamily.RELPERM, 2, (2,)),
    TableLayout("SLGOF", TableFamily.RELPERM, 4, (2, 3)),
    # fluid tables read at a depth (RSVD, PBVD, RVVD, PDVD) or a pressure (PVDG, PVDO)
    TableLayout("RSVD", TableFamily.FLUID, 2, (2,)),
    TableLayout("PBVD", TableFamily.FLUID, 2, (2,)),
    TableLayout("RVVD", TableFamily.FLUID, 2, (2,)),
    TableLayout("PDVD", TableFamily.FLUID, 2, (2,)),
    TableLayout("PVDG", TableFamily.FLUID, 3, (2, 3)),
    TableLayout("PVDO", TableFamily.FLUID, 3, (2, 3)),
)}


def editable(family: TableFamily) -> dict[str, tuple[int, ...]]:
    """The tables of ``family`` and the columns a parameter may edit in each."""
    return {k: t.editable for k, t in TABLES.items() if t.family == family}


def width(keyword: str) -> int:
    """The number of columns in a row of table ``keyword`` (KeyError for a table hmflow does
    not edit)."""
    return TABLES[keyword.upper()].width
