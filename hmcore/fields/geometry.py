"""Horizontal cell centres of a grid from the arrays its deck gives (pure numpy).

The arrays themselves come from OPM's parser (:mod:`hmcore.fields.grid`); this module only
does the geometry. Cells are in Eclipse's global order, i fastest then j then k, so an array
over all cells reshapes to ``(nz, ny, nx)``. The depth of a centre is OPM's own
(``EclipseGrid.getCellDepth``); what OPM's Python binding does not give is x and y.

* Corner-point grids (``COORD``/``ZCORN``): a cell's 8 corners lie on its 4 pillars (straight
  lines from ``(x, y, z)_top`` to ``(x, y, z)_bottom``) at the corners' ZCORN depths; the
  centre is the mean of the 8 corners.
* Block-centred grids: ``DX``/``DY`` per cell (summed along i and along j) or ``DXV``/``DYV``
  per column and row; the grid starts at x = y = 0.

Coordinates are the deck's own (no ``MAPAXES``), in its length unit: metres for METRIC.
"""

from __future__ import annotations

import numpy as np

Dims = tuple[int, int, int]


def corner_point_xy(dims: Dims, coord: np.ndarray, zcorn: np.ndarray) -> np.ndarray:
    """(x, y) of every cell's centre, shape ``(nx*ny*nz, 2)``, from ``coord`` (6 values per
    pillar: x, y, z at its top, then at its bottom; ``(nx+1)*(ny+1)`` pillars, i fastest)
    and ``zcorn`` (``8*nx*ny*nz`` corner depths: per layer the top face then the bottom
    face, each ``2nx * 2ny`` values with i fastest)."""
    nx, ny, nz = dims
    coord = np.asarray(coord, float)
    zcorn = np.asarray(zcorn, float)
    if coord.size != 6 * (nx + 1) * (ny + 1):
        raise ValueError(f"COORD has {coord.size} values; a {nx}x{ny}x{nz} grid needs "
                         f"6*(nx+1)*(ny+1) = {6 * (nx + 1) * (ny + 1)}")
    if zcorn.size != 8 * nx * ny * nz:
        raise ValueError(f"ZCORN has {zcorn.size} values; a {nx}x{ny}x{nz} grid needs "
                         f"8*nx*ny*nz = {8 * nx * ny * nz}")
    pillars = coord.reshape(ny + 1, nx + 1, 6)
    z = zcorn.reshape(2 * nz, 2 * ny, 2 * nx)
    x_sum = np.zeros((nz, ny, nx))
    y_sum = np.zeros((nz, ny, nx))
    for a in (0, 1):          # the pillar on the cell's low (0) or high (1) i side
        for b in (0, 1):      # ... and j side
            p = pillars[b:b + ny, a:a + nx]                  # (ny, nx, 6)
            xt, yt, zt, xb, yb, zb = (p[..., c] for c in range(6))
            dz = zb - zt
            vertical = np.abs(dz) < 1e-12                    # a vertical line's x, y are fixed
            for t in (0, 1):  # top or bottom face of the cell
                zc = z[t::2, b::2, a::2]                     # (nz, ny, nx)
                s = np.where(vertical, 0.0, (zc - zt) / np.where(vertical, 1.0, dz))
                x_sum += xt + s * (xb - xt)
                y_sum += yt + s * (yb - yt)
    return np.stack([x_sum.ravel() / 8.0, y_sum.ravel() / 8.0], axis=1)


def block_centred_xy(dims: Dims, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """(x, y) of every cell's centre, shape ``(nx*ny*nz, 2)``, of a block-centred grid:
    ``dx``/``dy`` per cell (``nx*ny*nz`` values) or per column/row (``DXV``, ``nx`` values;
    ``DYV``, ``ny`` values). x is the sum of the widths before the cell along i plus half its
    own, y likewise along j."""
    dx = _per_cell(np.asarray(dx, float), dims, axis=2, name="DX")
    dy = _per_cell(np.asarray(dy, float), dims, axis=1, name="DY")
    x = np.cumsum(dx, axis=2) - dx / 2.0
    y = np.cumsum(dy, axis=1) - dy / 2.0
    return np.stack([x.ravel(), y.ravel()], axis=1)


def _per_cell(v: np.ndarray, dims: Dims, axis: int, name: str) -> np.ndarray:
    """``v`` as a ``(nz, ny, nx)`` array: given per cell, or per index along ``axis`` only."""
    nx, ny, nz = dims
    shape = (nz, ny, nx)
    if v.size == nx * ny * nz:
        return v.reshape(shape)
    if v.size == shape[axis]:
        along = [1, 1, 1]
        along[axis] = shape[axis]
        return np.broadcast_to(v.reshape(along), shape)
    raise ValueError(f"{name} has {v.size} values; a {nx}x{ny}x{nz} grid needs one per cell "
                     f"({nx * ny * nz}) or one per {'ij'[2 - axis]} index ({shape[axis]})")
