"""The ensemble's steps without the flow: a prior read from the user's GRDECL files (one per
member, ERT's way) stored as it was given and written into a member's deck; the update from
the members' records with a failed member left out (a linear stand-in for the simulator);
the cases an ensemble refuses before anything runs. Nothing here runs OPM Flow (the deck is
parsed with OPM's parser: marked ``opm``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flows.inputs import ensemble_problems
from hmcore.cases import load_case
from hmcore.errors import CaseError
from hmcore.fields.assimilation import smoother_data, update
from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.grdecl import read_grdecl, write_grdecl
from hmcore.fields.members import INCLUDE_NAME, MemberSimulator, insert_grid_include
from hmcore.fields.smoother import TooFewRealizations
from hmcore.model.run_deck import prepare_run_deck
from storage import ArtifactStore
from storage.ensemble import ENSEMBLE_FILE, ensemble_step
from tasks.case import prepare_deck
from tasks.ensemble import prepare_ensemble, prior_step

SIZE, CELLS = 6, 500
FILES = """
[[parameters]]
name = "poro"
kind = "field"
keyword = "PORO"
prior = { source = "files", folder = "members", pattern = "poro_*.grdecl" }

[[parameters]]
name = "permx"
kind = "field"
keyword = "PERMX"
copies = ["PERMY"]
prior = { source = "files", folder = "members", pattern = "perm_*.grdecl" }

[ensemble]
size = 6
"""


class Recorder:
    """A stand-in for the simulator: keeps the deck it was given, runs nothing."""

    name = "recorder"

    def __init__(self):
        self.decks = []

    def run(self, deck: Path, run_dir: Path):
        self.decks.append(Path(deck).read_text())
        return run_dir


def copy_case(tmp_path: Path, small_case: Path, extra: str) -> Path:
    shutil.copytree(small_case.parent, tmp_path / "case", ignore=shutil.ignore_patterns("truth*"))
    case = tmp_path / "case" / "case.toml"
    case.write_text(case.read_text() + extra)
    return case


@pytest.mark.opm
def test_a_prior_read_from_grdecl_files_is_stored_and_run_as_given(tmp_path, small_case):
    case_file = copy_case(tmp_path, small_case, FILES)
    rng = np.random.default_rng(3)
    poro = rng.uniform(0.1, 0.3, (SIZE, CELLS)).round(5)
    perm = 10 ** rng.normal(1.5, 0.4, (SIZE, CELLS)).round(3)
    members = case_file.parent / "members"
    members.mkdir()
    for m in range(SIZE):  # poro_1 ... poro_6: member m is the m-th file in natural order
        write_grdecl(members / f"poro_{m + 1}.grdecl", {"PORO": poro[m]})
        write_grdecl(members / f"perm_{m + 1}.grdecl", {"PERMX": perm[m]})
    case = load_case(case_file)
    storage = str(tmp_path / "store")
    version = prepare_deck.fn(case, str(case_file), storage, "p")
    setup = prepare_ensemble.fn(case)
    prior = prior_step.fn(case, setup, storage, "p", version)
    table = prior.read_parquet(ENSEMBLE_FILE)
    for m in range(SIZE):
        column = table[f"m{m:04d}"].to_numpy()
        assert column.dtype == np.float32
        np.testing.assert_array_equal(column[:CELLS], poro[m].astype(np.float32))
        np.testing.assert_allclose(column[CELLS:], np.log10(perm[m]), rtol=1e-6)  # log space
    assert prior.read_json("ensemble.json")["sources"]["poro"] == f"files {members.resolve()}"
    again = prior_step.fn(case, setup, storage, "p", version)
    assert again.reused and again.version == prior.version  # stored once

    inner = Recorder()
    run_dir = tmp_path / "run"
    deck = prepare_run_deck(case.deck, {}, case.space, run_dir, case.info)
    MemberSimulator(inner, prior.file(ENSEMBLE_FILE), 4, case.fields, setup.grid,
                    setup.layout, case.info.keyword_names).run(deck, run_dir)
    written = read_grdecl(run_dir / INCLUDE_NAME)
    np.testing.assert_allclose(written["PORO"], poro[4], rtol=1e-6)
    np.testing.assert_allclose(written["PERMX"], perm[4], rtol=1e-5)
    np.testing.assert_array_equal(written["PERMY"], written["PERMX"])
    text = inner.decks[0]
    assert text.index("COPY") < text.index(INCLUDE_NAME) < text.index("\nPROPS")


def linear_records(X: np.ndarray, G: np.ndarray, failed: dict[int, str]) -> dict[int, dict]:
    """Records of a linear model ``residuals = G x - 1`` (the data: 1 everywhere), a failed
    member as a campaign records it (status FAIL, its failure kind, no residuals)."""
    return {m: ({"status": "FAIL", "failure": failed[m], "residuals": None} if m in failed
                else {"status": "COMPLETE", "residuals": (G @ X[m] - 1.0).tolist()})
            for m in range(X.shape[0])}


def test_a_failed_member_is_left_out_and_the_update_still_made():
    rng = np.random.default_rng(0)
    X = rng.normal(0.0, 1.0, (10, 30)).astype(np.float32)
    G = rng.normal(0.0, 0.3, (12, 30))
    data = smoother_data(["P1"] * 12, {"P1": np.array([0.0, 0.0])})
    spec = EnsembleSpec(size=10, weights=(1.0,), min_realizations=5, localisation="none")
    result = update(X, linear_records(X, G, {3: "crash"}), data, 0, spec)
    ok = [m for m in range(10) if m != 3]
    assert np.isnan(result.ensemble[3]).all() and result.left_out == (3,)
    assert np.isfinite(result.ensemble[ok]).all()
    before = np.mean([(G @ X[m] - 1.0) @ (G @ X[m] - 1.0) for m in ok])
    after = np.mean([(G @ x - 1.0) @ (G @ x - 1.0) for x in result.ensemble[ok]])
    assert after < 0.7 * before  # the update moved the members towards the data
    with pytest.raises(TooFewRealizations, match="4 of 10 members have results .6 failed "
                       "now, 0 left out before., fewer than min_realizations = 5"):
        update(X, linear_records(X, G, dict.fromkeys(range(6), "timeout")), data, 0, spec)


def test_the_members_fields_go_after_the_grid_section_or_the_deck_is_refused(tmp_path):
    keywords = frozenset({"GRID", "PORO", "COPY", "PROPS", "SWOF"})
    deck = "GRID\nPORO\n 4*0.2 /\nCOPY\n PERMX PERMY /\n/\nPROPS\nSWOF\n/\n"
    text = insert_grid_include(deck, tmp_path / "F.GRDECL", keywords)
    assert text.index("COPY") < text.index(f"INCLUDE\n  '{tmp_path / 'F.GRDECL'}' /") \
        < text.index("PROPS")
    with pytest.raises(CaseError, match="no section keyword .EDIT or PROPS. after GRID"):
        insert_grid_include("GRID\nPORO\n 4*0.2 /\nINCLUDE\n 'rest.inc' /\n",
                            tmp_path / "F.GRDECL", keywords)


@pytest.mark.opm
def test_an_ensemble_refuses_a_case_without_fields_or_with_a_multiplier_on_one(tmp_path,
                                                                               small_case):
    plain = load_case(small_case)
    [problem] = ensemble_problems(plain)
    assert "has no field parameter" in problem
    done = subprocess.run([sys.executable, "-m", "hmflow.cli", "ensemble", "--case",
                           str(small_case), "--storage", str(tmp_path / "store")],
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and "has no field parameter" in " ".join(done.stderr.split())
    assert not (tmp_path / "store").exists()  # refused before anything ran or was stored
    case = copy_case(tmp_path, small_case, """
[[parameters]]
name = "k"
kind = "multiply"
keywords = ["PERMX"]
low = 0.5
high = 2.0

[[parameters]]
name = "permx"
kind = "field"
keyword = "PERMX"
copies = ["PERMY"]
prior = { source = "geostatistical", seed = 1, zones = [{ layers = [1, 5], mean = 1.5, std = 0.3 }], variogram = { ranges = [1000.0, 1000.0, 2.0] } }
""")
    [problem] = ensemble_problems(load_case(case))
    assert "parameter 'k' multiplies PERMX, which field 'permx' sets in every member" in problem
    assert ensemble_step(0) == "ensemble-00" and ArtifactStore(tmp_path).latest(
        "x", ensemble_step(0)) is None
