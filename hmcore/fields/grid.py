"""The grid a field lives on: dimensions, active cells, their centres and the deck's own values,
read with OPM's parser (opm.io ``Parser``, ``EclipseState``, ``EclipseGrid``).

What opm.io 2026.4 gives from Python, and what this module adds:

* ``EclipseGrid``: ``nx, ny, nz``, ``nactive``, ``cartesianSize`` and ``getCellDepth()`` (the
  depth of every cell's centre) - used as they are;
* ``FieldProperties``: ``get_double_array`` / ``get_int_array`` of a keyword over the active
  cells, in global order (PERM* in SI units, converted to mD here), and ``in`` for the
  keywords the deck defines;
* no active-to-global map and no x, y of a centre. The active cells are the deck's ``ACTNUM``
  (all cells without one), accepted only when their count is OPM's ``nactive`` (cells OPM
  deactivates itself, by MINPV say, are refused with a :class:`~hmcore.errors.Problem`); x, y
  come from the deck's COORD/ZCORN or DX/DY (DXV/DYV) arrays, as OPM's parser expands them,
  through :mod:`hmcore.fields.geometry`.

Array shapes: ``active`` ``(n_active,)`` global indices (i fastest, then j, then k), ascending
(OPM's active order, the order of every per-active-cell array in hmcore.fields); ``centres``
``(n_active, 3)`` as x, y, depth in the deck's length unit.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import opm.io
from opm.io.ecl_state import EclipseState
from opm.io.parser import ParseContext, Parser

from hmcore.eclipse.deck_info import FLOW_TOLERATES, quiet_stdout  # the one guard of fd 1
from hmcore.errors import CaseError, Problem
from hmcore.fields.geometry import block_centred_xy, corner_point_xy
from hmcore.fields.spec import FIELD_KEYWORDS

MILLIDARCY_M2 = 9.869233e-16
"""opm.io gives permeability in m2; decks state it in mD."""
REGION_KEYWORDS = ("FIPNUM", "MULTNUM", "FLUXNUM", "OPERNUM", "SATNUM", "PVTNUM", "EQLNUM")


@dataclass(frozen=True, eq=False)
class FieldGrid:
    """A deck's grid as the field code needs it (see the module's docstring for shapes)."""

    dims: tuple[int, int, int]
    active: np.ndarray
    centres: np.ndarray
    values: Mapping[str, np.ndarray] = field(default_factory=dict)
    """The deck's own values per active cell of the keywords it defines (PERM* in mD)."""
    regions: Mapping[str, np.ndarray] = field(default_factory=dict)
    """Region numbers per active cell of the region keywords the deck defines."""
    source: str = ""

    def __post_init__(self) -> None:
        n = self.active.shape[0]
        if self.centres.shape != (n, 3):
            raise ValueError(f"centres must have shape (n_active, 3) = ({n}, 3), got "
                             f"{self.centres.shape}")
        if n and not (0 <= self.active[0] and self.active[-1] < self.n_total
                      and np.all(np.diff(self.active) > 0)):
            raise ValueError("active must hold ascending global indices inside the grid")

    @property
    def n_active(self) -> int:
        return int(self.active.shape[0])

    @property
    def n_total(self) -> int:
        nx, ny, nz = self.dims
        return nx * ny * nz

    @property
    def ijk(self) -> np.ndarray:
        """1-based (i, j, k) of the active cells, shape ``(n_active, 3)``."""
        nx, ny, _ = self.dims
        g = self.active
        return np.stack([g % nx + 1, (g // nx) % ny + 1, g // (nx * ny) + 1], axis=1)

    @property
    def keywords(self) -> frozenset[str]:
        """The field keywords the deck defines (PORO, PERMX, ...)."""
        return frozenset(self.values)

    def deck_values(self, keyword: str) -> np.ndarray:
        """The deck's own values of ``keyword`` per active cell; KeyError when undefined."""
        try:
            return self.values[keyword.upper()]
        except KeyError:
            raise KeyError(f"the deck defines no {keyword.upper()}; it defines "
                           f"{sorted(self.values) or 'none of ' + str(list(FIELD_KEYWORDS))}"
                           ) from None

    def full(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Per-active-cell ``values`` ``(n_active,)`` -> every cell ``(n_total,)``, ``fill``
        in the inactive ones."""
        values = np.asarray(values)
        if values.shape != (self.n_active,):
            raise ValueError(f"expected one value per active cell ({self.n_active}), got "
                             f"shape {values.shape}")
        out = np.full(self.n_total, fill, dtype=np.result_type(values.dtype, type(fill)))
        out[self.active] = values
        return out

    def centre_of(self, cells: list[tuple[int, int, int]]) -> np.ndarray:
        """Mean centre ``(3,)`` of 1-based (i, j, k) cells (a well's connections), whether
        active or not; ValueError for a cell outside the grid."""
        nx, ny, nz = self.dims
        ijk = np.asarray(cells, int).reshape(-1, 3)
        if ijk.size == 0 or np.any(ijk < 1) or np.any(ijk > (nx, ny, nz)):
            raise ValueError(f"cells must be 1-based (i, j, k) inside {nx}x{ny}x{nz}, got "
                             f"{ijk.tolist()}")
        g = (ijk[:, 0] - 1) + nx * (ijk[:, 1] - 1) + nx * ny * (ijk[:, 2] - 1)
        pos = np.searchsorted(self.active, g)
        hit = (pos < self.n_active) & (self.active[np.minimum(pos, self.n_active - 1)] == g)
        if not hit.any():
            raise ValueError(f"none of the cells {ijk.tolist()} is active")
        return self.centres[pos[hit]].mean(axis=0)


def read_grid(deck: Path | str) -> FieldGrid:
    """The grid of the deck at ``deck``, parsed with opm.io; CaseError listing the problems
    (OPM cannot parse it, active cells or geometry not known)."""
    path = Path(deck).resolve()
    try:
        with quiet_stdout():
            try:
                parsed = Parser().parse(str(path), ParseContext())
            except (RuntimeError, ValueError):  # what OPM Flow tolerates is only a warning
                tolerated = [(name, opm.io.action.warn) for name in FLOW_TOLERATES]
                parsed = Parser().parse(str(path), ParseContext(tolerated))
            state = EclipseState(parsed)
    except (RuntimeError, ValueError) as exc:  # opm.io's, with the parser's text
        raise CaseError([Problem(str(path), f"OPM cannot parse the deck: {exc}",
                                 "run OPM Flow on the deck by hand to see its full message")]
                        ) from exc
    return from_parsed(parsed, state, str(path))


def from_parsed(deck, state, source: str = "") -> FieldGrid:
    """The grid of an opm.io ``deck`` and its ``EclipseState`` (see :func:`read_grid`)."""
    grid, fp = state.grid(), state.field_props()
    dims = (int(grid.nx), int(grid.ny), int(grid.nz))
    problems: list[Problem] = []
    active = _active_cells(deck, dims, int(grid.nactive), source, problems)
    xy = _xy(deck, dims, source, problems)
    if problems:
        raise CaseError(problems)
    depth = np.asarray(grid.getCellDepth(), float)
    centres = np.column_stack([xy[active], depth[active]])
    values = {}
    for kw in FIELD_KEYWORDS:
        if kw in fp:
            arr = np.asarray(fp.get_double_array(kw), float)
            values[kw] = arr / MILLIDARCY_M2 if kw.startswith("PERM") else arr
    regions = {kw: np.asarray(fp.get_int_array(kw), int) for kw in REGION_KEYWORDS if kw in fp}
    return FieldGrid(dims, active, centres, values, regions, source)


def _active_cells(deck, dims, nactive: int, source: str, problems: list[Problem]) -> np.ndarray:
    total = dims[0] * dims[1] * dims[2]
    if "ACTNUM" in deck:
        actnum = np.asarray(deck["ACTNUM"].get_int_array(), int)
        if actnum.size != total:
            problems.append(Problem(source, f"ACTNUM has {actnum.size} values, the grid "
                                    f"{dims[0]}x{dims[1]}x{dims[2]} has {total} cells",
                                    "give ACTNUM for every cell in one keyword (no BOX)"))
            return np.arange(0)
        active = np.flatnonzero(actnum > 0)
    else:
        active = np.arange(total)
    if active.size != nactive:
        problems.append(Problem(source, f"OPM makes {nactive} cells active, the deck's ACTNUM "
                                f"{active.size}: OPM deactivates cells itself (MINPV, zero pore "
                                "volume) and does not say which",
                                "set ACTNUM = 0 in those cells, or lower MINPV"))
    return active


def _xy(deck, dims, source: str, problems: list[Problem]) -> np.ndarray:
    """(x, y) of every cell's centre from the deck's geometry keywords."""
    try:
        if "COORD" in deck and "ZCORN" in deck:
            return corner_point_xy(dims, deck["COORD"].get_raw_array(),
                                   deck["ZCORN"].get_raw_array())
        for x_kw, y_kw in (("DX", "DY"), ("DXV", "DYV")):
            if x_kw in deck and y_kw in deck:
                return block_centred_xy(dims, deck[x_kw].get_raw_array(),
                                        deck[y_kw].get_raw_array())
        what = "the deck has neither COORD and ZCORN nor DX and DY (nor DXV and DYV)"
    except ValueError as exc:
        what = str(exc)
    problems.append(Problem(source, f"the cell centres cannot be computed: {what}",
                            "give the grid as COORD/ZCORN, or DX/DY with a value per cell, "
                            "or DXV/DYV"))
    return np.zeros((dims[0] * dims[1] * dims[2], 2))
