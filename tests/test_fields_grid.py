"""The grid of a field: cell centres from corner-point and block-centred geometry (numpy), the
grid object's maps, and PUNQ-S3's grid read with opm.io (marked ``opm``: it parses the deck,
it simulates nothing)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hmcore.errors import CaseError
from hmcore.fields.geometry import block_centred_xy, corner_point_xy
from hmcore.fields.grid import FieldGrid, read_grid

PUNQ = Path(__file__).resolve().parents[2] / "shared" / "punqs3" / "PUNQS3.DATA"


def sheared_box(nx=3, ny=2, nz=2, dx=100.0, dy=50.0, shift=30.0, top=1000.0, dz=10.0):
    """COORD/ZCORN of a box whose pillars lean by ``shift`` in x over their height
    (``top`` to ``top + nz*dz``), with flat layers."""
    bottom = top + nz * dz
    pillars = [(i * dx, j * dy, top, i * dx + shift, j * dy, bottom)
               for j in range(ny + 1) for i in range(nx + 1)]
    z = np.empty((2 * nz, 2 * ny, 2 * nx))
    for k in range(nz):
        z[2 * k] = top + k * dz
        z[2 * k + 1] = top + (k + 1) * dz
    return np.ravel(pillars), z.ravel()


def test_corner_point_centres_follow_leaning_pillars():
    coord, zcorn = sheared_box()
    xy = corner_point_xy((3, 2, 2), coord, zcorn)
    assert xy.shape == (12, 2)
    # cell (i=0, j=0, k=0): depth 1000-1010 of 1000-1020, so pillars are shifted 7.5 m
    np.testing.assert_allclose(xy[0], [50.0 + 7.5, 25.0])
    # cell (i=2, j=1, k=1): depth 1010-1020, shifted 22.5 m
    np.testing.assert_allclose(xy[11], [250.0 + 22.5, 75.0])


def test_vertical_pillars_and_wrong_sizes():
    coord, zcorn = sheared_box(shift=0.0)
    coord = coord.reshape(-1, 6)
    coord[:, 5] = coord[:, 2]  # top and bottom at the same depth: x, y fixed
    xy = corner_point_xy((3, 2, 2), coord.ravel(), zcorn)
    np.testing.assert_allclose(xy[4], [150.0, 75.0])
    with pytest.raises(ValueError, match=r"COORD has 5 values; a 3x2x2 grid needs"):
        corner_point_xy((3, 2, 2), np.zeros(5), zcorn)
    with pytest.raises(ValueError, match=r"ZCORN has 3 values"):
        corner_point_xy((3, 2, 2), coord.ravel(), np.zeros(3))


def test_block_centred_centres_from_dx_dy_or_dxv_dyv():
    dims = (3, 2, 1)
    xy = block_centred_xy(dims, [10.0, 20.0, 30.0] * 2, [5.0] * 6)
    np.testing.assert_allclose(xy[:, 0], [5.0, 20.0, 45.0] * 2)
    np.testing.assert_allclose(xy[:, 1], [2.5] * 3 + [7.5] * 3)
    np.testing.assert_allclose(block_centred_xy(dims, [10.0, 20.0, 30.0], [5.0, 5.0]), xy)
    with pytest.raises(ValueError, match=r"DY has 4 values; .* one per cell \(6\) or one per "
                                         r"j index \(2\)"):
        block_centred_xy(dims, [1.0] * 3, [1.0] * 4)


def test_the_grid_maps_active_cells_to_the_whole_grid_and_back():
    active = np.array([1, 2, 5, 7])
    grid = FieldGrid((2, 2, 2), active, np.arange(12.0).reshape(4, 3), {"PORO": np.ones(4)})
    assert grid.n_total == 8 and grid.n_active == 4 and grid.keywords == {"PORO"}
    assert grid.ijk.tolist() == [[2, 1, 1], [1, 2, 1], [2, 1, 2], [2, 2, 2]]
    np.testing.assert_array_equal(grid.full(np.array([1.0, 2.0, 3.0, 4.0]), fill=-1.0),
                                  [-1, 1, 2, -1, -1, 3, -1, 4])
    np.testing.assert_allclose(grid.centre_of([(2, 1, 1), (2, 1, 2), (1, 1, 1)]),
                               [3.0, 4.0, 5.0])  # the inactive (1, 1, 1) is skipped
    with pytest.raises(KeyError, match="the deck defines no PERMX"):
        grid.deck_values("permx")
    with pytest.raises(ValueError, match="ascending global indices"):
        FieldGrid((2, 2, 2), np.array([3, 1]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="inside 2x2x2"):
        grid.centre_of([(3, 1, 1)])


@pytest.mark.opm
@pytest.mark.skipif(not PUNQ.is_file(), reason=f"PUNQ-S3 data not found at {PUNQ}")
def test_punqs3_grid_read_with_opm_io():
    grid = read_grid(PUNQ)
    assert grid.dims == (19, 28, 5) and grid.n_active == 1761 and grid.n_total == 2660
    assert grid.keywords == {"PORO", "PERMX", "PERMY", "PERMZ"}
    assert grid.deck_values("PERMX").shape == (1761,)
    assert 0.0 < grid.deck_values("PERMX").min() and grid.deck_values("PERMX").max() < 1e4  # mD
    x, y, depth = grid.centres.T
    # 180 m cells: centres on a 180 m lattice, from 90 m; depths of a ~2.4 km reservoir
    np.testing.assert_allclose((x - 90.0) % 180.0, 0.0, atol=1e-6)
    assert x.max() <= 19 * 180.0 and y.max() <= 28 * 180.0
    assert 2300.0 < depth.min() < depth.max() < 2450.0
    first = grid.ijk[0]
    assert tuple(first) == (15, 1, 1)  # PUNQ-S3's first active cell
    well = grid.centre_of([(10, 22, k) for k in (3, 4)])  # PRO-1's column
    np.testing.assert_allclose(well[:2], [9.5 * 180.0, 21.5 * 180.0])


def test_a_deck_opm_cannot_parse_is_one_problem(tmp_path):
    deck = tmp_path / "BAD.DATA"
    deck.write_text("RUNSPEC\nDIMENS\n 2 2 x /\n")
    with pytest.raises(CaseError, match="OPM cannot parse the deck"):
        read_grid(deck)
