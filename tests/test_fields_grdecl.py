"""A member's fields written as a GRDECL include and read back (OPM's parser reads them), the
transform between update space and physical values, and the user's GRDECL realisations
checked all at once. No simulator."""

from __future__ import annotations

import numpy as np
import pytest

from hmcore.fields.grdecl import (
    GrdeclError,
    format_values,
    member_arrays,
    read_grdecl,
    write_grdecl,
    write_member,
)
from hmcore.fields.grid import FieldGrid
from hmcore.fields.realisations import read_realisations
from hmcore.fields.spec import FieldSpec
from hmcore.fields.transform import to_physical, to_update_space

DIMS = (4, 3, 2)


def tiny_grid() -> FieldGrid:
    """4 x 3 x 2 cells, cells 0 and 13 inactive."""
    active = np.setdiff1d(np.arange(24), [0, 13])
    centres = np.column_stack([active % 4 * 10.0, active // 4 % 3 * 10.0, active // 12 + 1.0])
    values = {"PORO": np.full(22, 0.2), "PERMX": np.full(22, 50.0)}
    return FieldGrid(DIMS, active, centres, values, {}, "tiny")


GRID = tiny_grid()
PORO = FieldSpec.model_validate({"name": "poro", "keyword": "PORO", "low": 0.05, "high": 0.35,
                                 "prior": {"source": "files", "folder": "p"}})
PERM = FieldSpec.model_validate({"name": "permx", "keyword": "PERMX", "copies": ["PERMY"],
                                 "low": 1.0, "high": 2000.0,
                                 "prior": {"source": "files", "folder": "k"}})


def test_update_space_is_log10_for_permeability_and_values_are_truncated_to_bounds():
    assert to_update_space(np.array([1.0, 100.0]), PERM).tolist() == [0.0, 2.0]
    assert to_update_space(np.array([0.2]), PORO).dtype == np.float32
    np.testing.assert_allclose(to_physical(np.array([-1.0, 2.0, 5.0]), PERM), [1.0, 100.0, 2000.0])
    np.testing.assert_allclose(to_physical(np.array([-0.1, 0.2, 0.9]), PORO), [0.05, 0.2, 0.35])
    assert to_physical(np.array([400.0]), PERM)[0] == 2000.0  # 10**400 overflows: still high
    with pytest.raises(ValueError, match="log space and needs values > 0"):
        to_update_space(np.array([5.0, 0.0]), PERM)
    with pytest.raises(ValueError, match="not finite"):
        to_physical(np.array([np.nan]), PERM)


def test_a_member_round_trips_through_its_include(tmp_path):
    rng = np.random.default_rng(0)
    u = {"poro": rng.uniform(0.1, 0.3, GRID.n_active).astype(np.float32),
         "permx": rng.uniform(0.5, 3.0, GRID.n_active).astype(np.float32)}
    path = write_member(tmp_path / "member_007.grdecl", [PORO, PERM], u, GRID,
                        header="hmflow member 7\niteration 0")
    text = path.read_text()
    assert text.startswith("-- hmflow member 7\n-- iteration 0\nPORO\n")
    back = read_grdecl(path)
    assert list(back) == ["PORO", "PERMX", "PERMY"]
    for keyword in back:
        assert back[keyword].shape == (24,)
        assert back[keyword][0] == 0.0 and back[keyword][13] == 0.0  # inactive cells
    np.testing.assert_allclose(back["PORO"][GRID.active], u["poro"], rtol=1e-6)
    np.testing.assert_allclose(back["PERMX"][GRID.active], 10.0 ** u["permx"].astype(float),
                               rtol=1e-6)
    np.testing.assert_array_equal(back["PERMY"], back["PERMX"])
    # back to update space: the member again, to float32 precision
    again = to_update_space(back["PERMX"][GRID.active], PERM)
    np.testing.assert_allclose(again, u["permx"], atol=1e-6)


def test_runs_of_equal_values_are_written_with_repeat_counts():
    assert format_values(np.array([0.0, 0.0, 0.0, 0.0, 0.5, 0.5, 1.0])) == " 4*0 0.5 0.5 1"
    many = format_values(np.arange(13.0))
    assert many.splitlines() == [" 0 1 2 3 4 5", " 6 7 8 9 10 11", " 12"]


def test_member_arrays_truncate_and_refuse_a_left_out_member():
    arrays = member_arrays([PORO], {"poro": np.full(GRID.n_active, 0.9)}, GRID)
    assert arrays["PORO"][GRID.active].max() == pytest.approx(0.35)
    with pytest.raises(ValueError, match="not finite"):
        member_arrays([PORO], {"poro": np.full(GRID.n_active, np.nan)}, GRID)
    with pytest.raises(ValueError, match="not finite"):
        write_grdecl("unused.grdecl", {"PORO": np.array([np.inf])})


def test_opm_s_message_is_kept_for_a_file_it_refuses(tmp_path):
    (tmp_path / "bad.grdecl").write_text("PORO\n 0.1 0.2 x /\n")
    with pytest.raises(GrdeclError, match="Malformed floating point number 'x'"):
        read_grdecl(tmp_path / "bad.grdecl")
    with pytest.raises(GrdeclError, match="no such file"):
        read_grdecl(tmp_path / "missing.grdecl")


def _write(folder, name, text):
    folder.mkdir(exist_ok=True)
    (folder / name).write_text(text)


def test_user_realisations_are_read_in_natural_order_in_update_space(tmp_path):
    folder = tmp_path / "k"
    for m in (1, 2, 10):  # natural order: 1, 2, 10 (not 1, 10, 2)
        _write(folder, f"permx_{m}.grdecl", f"PERMX\n 24*{10.0 ** m} /\n")
    _write(folder, "permx_3.grdecl", "PERMX\n 22*1000 /\n")  # active cells only: accepted
    members, problems = read_realisations(PERM, folder, GRID, 4)
    assert problems == []
    assert members.shape == (4, 22) and members.dtype == np.float32
    np.testing.assert_allclose(members[:, 0], [1.0, 2.0, 3.0, 10.0])


def test_every_problem_of_the_user_s_realisations_is_reported_at_once(tmp_path):
    folder = tmp_path / "k"
    _write(folder, "m0.grdecl", "PERMX\n 24*100 /\n")                    # fine
    _write(folder, "m1.grdecl", "PERMX\n 20*100 /\n")                    # wrong count
    _write(folder, "m2.grdecl", "PORO\n 24*0.2 /\n")                     # keyword missing
    _write(folder, "m3.grdecl", "PERMX\n 3*100 -5 20*100 /\n")           # not positive
    _write(folder, "m4.grdecl", "PERMX\n 24*100\n")                      # not terminated
    members, problems = read_realisations(PERM, folder, GRID, 6)
    assert members is None
    text = "\n".join(str(p) for p in problems)
    assert "the ensemble has 6 members but 5 file(s) match '*.grdecl'" in text
    assert "m1.grdecl: PERMX has 20 values; the grid 4x3x2 has 24 cells, 22 of them active" \
        in text
    assert "m2.grdecl: has no PERMX; it has ['PORO']" in text
    assert "m3.grdecl: PERMX must be > 0" in text and "-5.0 in cell (i, j, k) = (4, 1, 1)" \
        in text
    assert "m4.grdecl: OPM's parser refuses the file" in text
    assert len(problems) == 5


def test_porosity_outside_zero_one_and_a_missing_folder_are_problems(tmp_path):
    _write(tmp_path / "p", "a.grdecl", "PORO\n 23*0.2 1.5 /\n")
    members, problems = read_realisations(PORO, tmp_path / "p", GRID, 1)
    assert members is None and "PORO must be in [0, 1] (a fraction)" in problems[0].what
    members, problems = read_realisations(PORO, tmp_path / "nowhere", GRID, 1)
    assert members is None and "is not a folder" in problems[0].what
