"""Which active cells a prior's zones hold, and the checks of zones and keywords against the
deck's grid (every problem at once, before any draw or run)."""

from __future__ import annotations

import numpy as np

from hmcore.errors import Problem
from hmcore.fields.grid import FieldGrid
from hmcore.fields.spec import FieldSpec, Zone


def zone_mask(zone: Zone, grid: FieldGrid) -> np.ndarray:
    """The active cells of ``zone``, a boolean ``(n_active,)``: its layers k1..k2, or the
    cells of its region number (none when the deck lacks the region keyword)."""
    if zone.layers is not None:
        k = grid.ijk[:, 2]
        return (k >= zone.layers[0]) & (k <= zone.layers[1])
    numbers = grid.regions.get(zone.region.upper())  # type: ignore[union-attr]
    return np.zeros(grid.n_active, bool) if numbers is None else numbers == zone.number


def prior_problems(fields: list[FieldSpec] | tuple[FieldSpec, ...],
                   grid: FieldGrid) -> list[Problem]:
    """Every problem of the fields' priors on this grid: keyword not defined by the deck, zone
    outside the grid or without active cells, region keyword unknown, zones overlapping or
    leaving active cells out. ``where`` is ``field '<name>'`` (the caller adds the case
    file). The user's files are checked by :func:`hmcore.fields.realisations.read_realisations`."""
    problems = []
    nz = grid.dims[2]
    for f in fields:
        where = f"field '{f.name}'"
        if f.keyword not in grid.keywords:
            problems.append(Problem(where, f"the deck defines no {f.keyword}; it defines "
                                    f"{sorted(grid.keywords)}", "define it in the GRID section"))
        zones = getattr(f.prior, "zones", ())
        count = np.zeros(grid.n_active, int)
        for zone in zones:
            at = f"{where} zone {zone.label()}"
            if zone.layers is not None and zone.layers[1] > nz:
                problems.append(Problem(at, f"layers must lie in 1..{nz}, got "
                                        f"{list(zone.layers)}", "use the deck's k indices"))
            elif zone.region is not None and zone.region.upper() not in grid.regions:
                problems.append(Problem(at, f"the deck defines no {zone.region.upper()}; it "
                                        f"defines {sorted(grid.regions) or 'no region keyword'}",
                                        "use a region keyword of the deck"))
            mask = zone_mask(zone, grid)
            if not mask.any():
                problems.append(Problem(at, "the zone has no active cell",
                                        "remove it or give other layers or another number"))
            count += mask
        if zones and (count != 1).any():
            ijk = grid.ijk[count != 1][0].tolist()
            problems.append(Problem(where, f"every active cell must be in exactly one zone; "
                                    f"{int((count == 0).sum())} are in none and "
                                    f"{int((count > 1).sum())} in several (e.g. cell {ijk})",
                                    "make the zones' layers or regions cover the grid once"))
    return problems
