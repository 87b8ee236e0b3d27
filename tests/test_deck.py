"""The deck editor (hmcore.model.run_deck): per-run decks with MULTIPLY and skin edits, base never touched.

Edited decks are checked with OPM's own parser (opm.io), not with hmflow's lexer: keyword
order, COMPDAT item 11, grid properties after MULTIPLY and connection factors. One real OPM
Flow run confirms in the INIT file that the multipliers act exactly.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from conftest import (PUNQ_DECK, PUNQ_DECK_FILES, PUNQ_DIR, copy_punq_deck, requires_opm,
                      requires_punq, sha256_file)
from hmcore.model.run_deck import Multiply, edits_for, prepare_run_deck, render_deck
from hmcore.eclipse.deck_info import DeckInfo, quiet_stdout
from hmcore.errors import CaseError
from hmcore.model.parameters import Parameter, ParameterSpace

pytestmark = [requires_punq, requires_opm]

MULTS = {"poro_mult": 1.1, "permx_mult": 2.0, "permy_mult": 0.5, "permz_mult": 1.5}
PRODUCER_CONNECTIONS = {  # (well, k) of the 11 COMPDAT lines of PUNQS3.DATA
    ("PRO-1", 5), ("PRO-1", 4), ("PRO-4", 5), ("PRO-4", 4), ("PRO-5", 4), ("PRO-5", 3),
    ("PRO-11", 4), ("PRO-11", 3), ("PRO-12", 5), ("PRO-12", 4), ("PRO-15", 4)}


# ----------------------------------------------------------------------------- OPM helpers
def opm_parse(deck: Path):
    from opm.io.ecl_state import EclipseState
    from opm.io.parser import ParseContext, Parser
    from opm.io.schedule import Schedule

    with quiet_stdout():
        d = Parser().parse(str(deck), ParseContext())
        state = EclipseState(d)
        schedule = Schedule(d, state)
    return d, state, schedule


def keyword_names(deck: Path) -> list[str]:
    return [kw.name for kw in opm_parse(deck)[0]]


def compdat_skins(deck: Path) -> dict[tuple[str, int], float]:
    """(well, k) -> COMPDAT item 11 as OPM's parser reads it (single-layer records only)."""
    d = opm_parse(deck)[0]
    out = {}
    for kw in d:
        if kw.name != "COMPDAT":
            continue
        for rec in kw:
            assert rec[10].name() == "SKIN"
            well, k1, k2 = rec[0].get_str(0), rec[3].get_int(0), rec[4].get_int(0)
            for k in range(k1, k2 + 1):
                out[(well, k)] = rec[10].get_raw(0)
    return out


def connection_factors(deck: Path) -> dict[tuple[str, int], float]:
    _, _, schedule = opm_parse(deck)
    step = len(schedule.reportsteps) - 1
    return {(w, c.k + 1): c.cf for w in schedule.well_names("*")
            for c in schedule.get_well(w, step).connections()}


def field_prop(deck: Path, kw: str) -> np.ndarray:
    return np.asarray(opm_parse(deck)[1].field_props().get_double_array(kw))


@pytest.fixture(scope="module")
def info() -> DeckInfo:
    return DeckInfo.inspect(PUNQ_DECK)


@pytest.fixture(scope="module")
def space() -> ParameterSpace:
    return ParameterSpace.reference()


@pytest.fixture(scope="module")
def base_run_deck(tmp_path_factory, info, space) -> Path:
    """The unmodified deck written by prepare_run_deck (INCLUDE paths absolute)."""
    return prepare_run_deck(PUNQ_DECK, {}, space, tmp_path_factory.mktemp("base"), info)


def skin_space(**kw) -> ParameterSpace:
    return ParameterSpace(parameters=(Parameter(name="s", kind="skin", low=-5, high=15, **kw),))


# ----------------------------------------------------------------------------- base deck
def test_base_deck_is_never_modified(tmp_path, space):
    deck = copy_punq_deck(tmp_path / "base")
    before = {n: sha256_file(tmp_path / "base" / n) for n in PUNQ_DECK_FILES}
    shared_before = {n: sha256_file(PUNQ_DIR / n) for n in PUNQ_DECK_FILES}
    info = DeckInfo.inspect(deck)
    for i, values in enumerate([{**MULTS, "skin": 9.0}, {"skin": -2.0}, {}]):
        prepare_run_deck(deck, values, space, tmp_path / f"run{i}", info)
    # the same via the shared deck (read-only there, but hash it anyway)
    prepare_run_deck(PUNQ_DECK, {**MULTS, "skin": 9.0}, space, tmp_path / "run_shared")
    assert {n: sha256_file(tmp_path / "base" / n) for n in PUNQ_DECK_FILES} == before
    assert {n: sha256_file(PUNQ_DIR / n) for n in PUNQ_DECK_FILES} == shared_before
    assert sorted(p.name for p in (tmp_path / "base").iterdir()) == sorted(PUNQ_DECK_FILES)
    # only the DATA file is written to a run dir: unchanged include files are not copied
    assert sorted(p.name for p in (tmp_path / "run0").iterdir()) == ["PUNQS3.DATA"]


def test_prepare_run_deck_refuses_to_overwrite(tmp_path, info, space):
    first = prepare_run_deck(PUNQ_DECK, {"skin": 1.0}, space, tmp_path / "run", info)
    text = first.read_text()
    with pytest.raises(FileExistsError):
        prepare_run_deck(PUNQ_DECK, {"skin": 2.0}, space, tmp_path / "run", info)
    assert first.read_text() == text


def test_unknown_parameter_is_rejected(info, space):
    with pytest.raises(KeyError, match="skinn"):
        edits_for(space, {"skinn": 1.0}, info)


# ----------------------------------------------------------------------------- MULTIPLY
def test_multiply_lands_after_copy_and_before_props(tmp_path, info, space):
    deck = prepare_run_deck(PUNQ_DECK, MULTS, space, tmp_path / "run", info)
    names = keyword_names(deck)
    assert names.count("MULTIPLY") == 1
    pos = {k: names.index(k) for k in ("GRID", "COPY", "MULTIPLY", "PROPS")}
    assert pos["GRID"] < pos["COPY"] < pos["MULTIPLY"] < pos["PROPS"]
    assert names.index("MULTIPLY") == names.index("PROPS") - 1
    # the records, as OPM reads them
    d = opm_parse(deck)[0]
    mult = next(kw for kw in d if kw.name == "MULTIPLY")
    records = {rec[0].get_str(0): rec[1].get_raw(0) for rec in mult}
    assert records == {"PORO": 1.1, "PERMX": 2.0, "PERMY": 0.5, "PERMZ": 1.5}


def test_multiplied_properties_as_opm_sees_them(tmp_path, base_run_deck, info, space):
    deck = prepare_run_deck(PUNQ_DECK, MULTS, space, tmp_path / "run", info)
    for kw, f in [("PORO", 1.1), ("PERMX", 2.0), ("PERMY", 0.5), ("PERMZ", 1.5)]:
        base, new = field_prop(base_run_deck, kw), field_prop(deck, kw)
        np.testing.assert_allclose(new, f * base, rtol=1e-12)
    # PERMY is a copy of PERMX in the base deck, so it gets its own factor only after COPY
    np.testing.assert_allclose(field_prop(deck, "PERMY"), 0.25 * field_prop(deck, "PERMX"),
                               rtol=1e-12)


def test_multiply_with_no_section_after_grid_is_a_case_error(tmp_path):
    deck = copy_punq_deck(tmp_path / "d")
    info = DeckInfo.inspect(deck)
    text = deck.read_text()
    # cut everything from PROPS on: the GRID section is then the last one
    deck.write_text(text[: text.index("PROPS    ====")])
    with pytest.raises(CaseError, match="no section keyword"):
        render_deck(info, [Multiply("PORO", 1.1)])


# ----------------------------------------------------------------------------- skin
def test_skin_rewritten_for_all_producers(tmp_path, base_run_deck, info, space):
    deck = prepare_run_deck(PUNQ_DECK, {"skin": 7.5}, space, tmp_path / "run", info)
    skins = compdat_skins(deck)
    assert set(skins) == PRODUCER_CONNECTIONS
    assert all(v == 7.5 for v in skins.values())
    assert all(v == 5.0 for v in compdat_skins(base_run_deck).values())
    # a larger skin lowers every connection factor (CF ~ 1 / (ln(r0/rw) + S))
    cf_base, cf_new = connection_factors(base_run_deck), connection_factors(deck)
    assert set(cf_new) == PRODUCER_CONNECTIONS
    assert all(cf_new[c] < cf_base[c] for c in PRODUCER_CONNECTIONS)


def test_skin_for_one_well_and_one_layer_only(tmp_path, base_run_deck, info):
    space = skin_space(wells=("PRO-4",), layers=(4,))
    deck = prepare_run_deck(PUNQ_DECK, {"s": 12.0}, space, tmp_path / "run", info)
    skins = compdat_skins(deck)
    assert skins[("PRO-4", 4)] == 12.0
    assert all(v == 5.0 for c, v in skins.items() if c != ("PRO-4", 4))
    cf_base, cf_new = connection_factors(base_run_deck), connection_factors(deck)
    assert cf_new[("PRO-4", 4)] < cf_base[("PRO-4", 4)]
    assert all(cf_new[c] == cf_base[c] for c in PRODUCER_CONNECTIONS if c != ("PRO-4", 4))


def test_skin_for_one_well_all_layers(tmp_path, info):
    space = skin_space(wells=("PRO-12",))
    deck = prepare_run_deck(PUNQ_DECK, {"s": -1.5}, space, tmp_path / "run", info)
    skins = compdat_skins(deck)
    assert skins[("PRO-12", 5)] == skins[("PRO-12", 4)] == -1.5
    assert all(v == 5.0 for (w, _), v in skins.items() if w != "PRO-12")


def test_multi_layer_compdat_record_is_split_for_a_layer_skin(tmp_path):
    deck = copy_punq_deck(tmp_path / "d")
    text = deck.read_text()
    one = "'PRO-1'    10   22   5   5   'OPEN'   2*  0.15  1*  5.0 /\n"
    two = "'PRO-1'    10   22   4   4   'OPEN'   2*  0.15  1*  5.0 /\n"
    assert one in text and two in text
    merged = "'PRO-1' 10 22 4 5 'OPEN' 2* 0.15 1* 5.0 /\n"  # one record for layers 4-5
    deck.write_text(text.replace(one, "").replace(two, merged))
    info = DeckInfo.inspect(deck)
    space = skin_space(wells=("PRO-1",), layers=(5,))
    run = prepare_run_deck(deck, {"s": 9.0}, space, tmp_path / "run", info)
    skins = compdat_skins(run)
    assert skins[("PRO-1", 5)] == 9.0 and skins[("PRO-1", 4)] == 5.0
    assert all(v == 5.0 for (w, _), v in skins.items() if w != "PRO-1")


def test_skin_and_multipliers_together(tmp_path, info, space):
    deck = prepare_run_deck(PUNQ_DECK, {**MULTS, "skin": 0.0}, space, tmp_path / "run", info)
    assert set(compdat_skins(deck).values()) == {0.0}
    assert keyword_names(deck).count("MULTIPLY") == 1


# ----------------------------------------------------------------------------- INCLUDE
def _include_paths(text: str) -> list[str]:
    lines = [l for l in text.splitlines() if not l.lstrip().startswith("--")]
    out = []
    for i, l in enumerate(lines):
        if l.strip() == "INCLUDE":
            m = re.search(r"'([^']+)'", lines[i + 1])
            out.append(m.group(1))
    return out


def test_include_paths_become_absolute(tmp_path, info, space):
    deck = prepare_run_deck(PUNQ_DECK, {**MULTS, "skin": 3.0}, space, tmp_path / "run", info)
    paths = _include_paths(deck.read_text())
    assert sorted(Path(p).name for p in paths) == ["PUNQS3.GEO", "PUNQS3.PRP"]
    for p in paths:
        assert Path(p).is_absolute() and Path(p).is_file()
        assert Path(p).resolve().parent == PUNQ_DIR.resolve()
    # grid data is referenced, not copied: the per-run deck stays small
    assert deck.stat().st_size < 50_000


def _move_compdat_to_include(deck: Path, inc_name: str) -> Path:
    text = deck.read_text()
    start = text.index("\nCOMPDAT\n") + 1
    end = text.index("\n/\n", start) + 3
    (deck.parent / inc_name).write_text(text[start:end])
    deck.write_text(text[:start] + f"INCLUDE\n  '{inc_name}' /\n" + text[end:])
    return deck.parent / inc_name


def test_compdat_in_an_include_file_is_inlined_and_edited(tmp_path, base_run_deck):
    deck = copy_punq_deck(tmp_path / "d")
    inc = _move_compdat_to_include(deck, "PUNQS3_WELLS.INC")
    info = DeckInfo.inspect(deck)  # the rearranged base deck is valid
    hashes = {p.name: sha256_file(p) for p in (tmp_path / "d").iterdir()}
    run = prepare_run_deck(deck, {"skin": 8.0}, ParameterSpace.reference(), tmp_path / "run", info)
    text = run.read_text()
    assert "PUNQS3_WELLS.INC" not in " ".join(_include_paths(text))
    assert re.search(r"^COMPDAT\s*$", text, re.M), "COMPDAT must be inlined in the run deck"
    skins = compdat_skins(run)
    assert set(skins) == PRODUCER_CONNECTIONS and set(skins.values()) == {8.0}
    # the other includes stay referenced (absolute), the base files are untouched
    assert sorted(Path(p).name for p in _include_paths(text)) == ["PUNQS3.GEO", "PUNQS3.PRP"]
    assert {p.name: sha256_file(p) for p in (tmp_path / "d").iterdir()} == hashes
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["PUNQS3.DATA"]
    assert all(v == 5.0 for v in compdat_skins(deck).values()) and inc.is_file()


def test_include_without_edits_is_referenced_not_inlined(tmp_path):
    deck = copy_punq_deck(tmp_path / "d")
    _move_compdat_to_include(deck, "PUNQS3_WELLS.INC")
    info = DeckInfo.inspect(deck)
    run = prepare_run_deck(deck, MULTS, ParameterSpace.reference(), tmp_path / "run", info)
    paths = _include_paths(run.read_text())
    assert str((tmp_path / "d" / "PUNQS3_WELLS.INC").resolve()) in paths
    assert set(compdat_skins(run).values()) == {5.0}


# ----------------------------------------------------------------------------- parsing
def test_written_deck_parses_with_opm(tmp_path, info, space):
    deck = prepare_run_deck(PUNQ_DECK, {**MULTS, "skin": 6.0}, space, tmp_path / "run", info)
    _, state, schedule = opm_parse(deck)
    assert state.grid().nactive == info.nactive
    assert sorted(schedule.well_names("*")) == sorted(info.wells)
    assert len(schedule.reportsteps) == len(info.report_days)


# regression: the lexer used to split quoted paths at "/" (INCLUDE '/abs/path' was "not found")
def test_written_deck_passes_deckinfo_inspect(tmp_path, info, space):
    deck = prepare_run_deck(PUNQ_DECK, {**MULTS, "skin": 6.0}, space, tmp_path / "run", info)
    written = DeckInfo.inspect(deck)
    assert written.dims == info.dims and written.nactive == info.nactive
    assert sorted(written.wells) == sorted(info.wells)
    assert written.report_days == info.report_days
    for kw, f in [("PORO", 1.1), ("PERMX", 2.0), ("PERMY", 0.5), ("PERMZ", 1.5)]:
        assert written.properties[kw][1] == pytest.approx(f * info.properties[kw][1], rel=1e-9)


# ----------------------------------------------------------------------------- real run
@pytest.mark.opm
def test_multipliers_act_exactly_in_the_init_file(opm_runs, truth_run):
    from opm.io.ecl import EclFile

    run = opm_runs.run(MULTS)
    base = EclFile(str(truth_run.run_dir / "PUNQS3.INIT"))
    new = EclFile(str(run.run_dir / "PUNQS3.INIT"))
    for kw, f in [("PORO", 1.1), ("PERMX", 2.0), ("PERMY", 0.5), ("PERMZ", 1.5)]:
        b = np.asarray(base[kw], dtype=float)
        n = np.asarray(new[kw], dtype=float)
        assert b.shape == n.shape == (1761,)
        assert (b > 0).all()
        # INIT stores float32: the ratio is the factor to float32 precision
        np.testing.assert_allclose(n / b, f, rtol=2e-7)
    # pore volume follows porosity
    np.testing.assert_allclose(np.asarray(new["PORV"], float)[np.asarray(base["PORV"]) > 0]
                               / np.asarray(base["PORV"], float)[np.asarray(base["PORV"]) > 0],
                               1.1, rtol=2e-6)


def test_a_deck_with_absolute_includes_can_be_a_base_deck(tmp_path, base_run_deck, space):
    # the per-run deck (absolute INCLUDE paths) is itself a valid base for another run
    info = DeckInfo.inspect(base_run_deck)
    run = prepare_run_deck(base_run_deck, {"skin": 2.0}, space, tmp_path / "run", info)
    assert set(compdat_skins(run).values()) == {2.0}
    assert sorted(Path(p).name for p in _include_paths(run.read_text())) == ["PUNQS3.GEO",
                                                                             "PUNQS3.PRP"]


def _scan_comment(line: str) -> str:
    """The rule, scanned character by character: a ``--`` outside quotes starts a comment."""
    quote = None
    for i, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif line.startswith("--", i):
            return line[:i]
    return line


def test_strip_comment_keeps_quoted_dashes_and_cuts_the_first_comment():
    from hypothesis import given, settings, strategies as st

    from hmcore.eclipse.lexer import strip_comment

    assert strip_comment("'PRO--1' 1 1 / -- a well") == "'PRO--1' 1 1 / "
    assert strip_comment("2* 0.5 --") == "2* 0.5 "

    @settings(max_examples=400, deadline=None)
    @given(st.text(alphabet="ab -'\"/1*", max_size=40))
    def agrees(line):
        assert strip_comment(line) == _scan_comment(line)

    agrees()
