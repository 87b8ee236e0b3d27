"""The base deck's per-cell properties, and the per-cell multipliers a parameter vector applies.

Read once from OPM's own parser (opm.io ``EclipseState``) when the case is loaded: the 1-based
(i, j, k) of every active cell, PORO, PERMX/PERMY/PERMZ in mD and the pore volume PORV. The
physics checks (:mod:`hmcore.scoring.physics`) compare a proposal's scaled cells with these, so a check
can say "kv/kh leaves [0.001, 1] in 34 % of the cells" before any simulator time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MILLIDARCY_M2 = 9.869233e-16  # opm.io returns permeability in SI units (m2)
CELL_KEYWORDS = ("PORO", "PERMX", "PERMY", "PERMZ", "PORV")
REGION_KEYWORDS = ("MULTNUM", "FLUXNUM", "OPERNUM", "FIPNUM")
Box = tuple[int, int, int, int, int, int]
Region = tuple[str, tuple[int, ...]]  # (region keyword, region numbers)


@dataclass(frozen=True, eq=False)
class CellProperties:
    """Active cells of the base deck: ``ijk`` (n, 3) 1-based, ``arrays[kw]`` (n,) per keyword
    (PERM* in mD; keywords the deck does not define are absent)."""

    ijk: np.ndarray | None          # None: positions unknown (a box then reaches every cell)
    arrays: dict[str, np.ndarray]
    regions: dict[str, np.ndarray] | None = None  # region keyword -> (n,) region numbers

    @property
    def n(self) -> int:
        return int(next(iter(self.arrays.values())).size) if self.arrays else 0

    def get(self, keyword: str) -> np.ndarray | None:
        return self.arrays.get(keyword.upper())

    @staticmethod
    def from_parsed(deck, state) -> "CellProperties":
        """From opm.io's parsed ``deck`` and its ``EclipseState`` (active cells, in its order)."""
        grid, fp = state.grid(), state.field_props()
        arrays = {}
        for kw in CELL_KEYWORDS:
            if kw in fp:
                arr = np.asarray(fp.get_double_array(kw), float)
                arrays[kw] = arr / MILLIDARCY_M2 if kw.startswith("PERM") else arr
        regions = {kw: np.asarray(fp.get_int_array(kw), int) for kw in REGION_KEYWORDS
                   if kw in fp}
        return CellProperties(_active_ijk(deck, grid), arrays, regions)

    def factors(self, multipliers: list[tuple[str, float, Box | Region | None]]
                ) -> dict[str, np.ndarray]:
        """Per-cell factor of each keyword after ``(keyword, factor, where)`` multipliers:
        ``where`` is None (every cell), a 1-based inclusive box ``(i1, i2, j1, j2, k1, k2)``
        or a region ``("MULTNUM", (2, 3))``; keywords never named are absent."""
        out: dict[str, np.ndarray] = {}
        for keyword, factor, where in multipliers:
            f = out.setdefault(keyword.upper(), np.ones(self.n))
            f[self.mask(where)] *= factor
        return out

    def mask(self, where: Box | Region | None) -> np.ndarray:
        if where is not None and isinstance(where[0], str):
            keyword, numbers = where
            arr = (self.regions or {}).get(str(keyword).upper())
            if arr is None:  # not defined in the deck: every cell is region 1
                return np.full(self.n, 1 in numbers)
            return np.isin(arr, numbers)
        return self.in_box(where)

    def in_box(self, box: tuple[int, ...] | None) -> np.ndarray:
        """Mask of the active cells inside a 1-based inclusive box (all cells when None)."""
        if box is None or self.ijk is None:  # unknown positions: conservative, every cell
            return np.ones(self.n, bool)
        i1, i2, j1, j2, k1, k2 = box
        i, j, k = self.ijk.T
        return (i >= i1) & (i <= i2) & (j >= j1) & (j <= j2) & (k >= k1) & (k <= k2)


def _active_ijk(deck, grid) -> np.ndarray | None:
    """1-based (i, j, k) of the active cells in opm.io's active order (global order).

    opm.io exposes no active-to-global map, so the active cells are taken from the deck's
    ACTNUM (all cells without one); when that count differs from the grid's (cells the
    simulator deactivates itself, e.g. by pore volume), None: cell positions unknown."""
    nx, ny, nz = grid.nx, grid.ny, grid.nz
    total = nx * ny * nz
    if "ACTNUM" in deck:
        actnum = np.asarray(deck["ACTNUM"][0][0].get_data_list(), int)
        g = np.flatnonzero(actnum > 0) if actnum.size == total else np.arange(0)
    else:
        g = np.arange(total)
    if g.size != grid.nactive:
        return None
    return np.stack([g % nx + 1, (g // nx) % ny + 1, g // (nx * ny) + 1], axis=1)
