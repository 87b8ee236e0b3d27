"""Field parameters and the ``[ensemble]`` section in a case file: a PUNQ-S3 case with porosity
and permeability fields loads and ``hmflow check`` prints it; bad field specifications are
refused before any run, every problem at once with the case file and the key.

The deck is parsed with OPM's parser (marked ``opm``); nothing is simulated.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from conftest import PUNQ_DECK, requires_opm, requires_punq, write_case_toml
from typer.testing import CliRunner

from hmcore.cases import load_case
from hmcore.errors import CaseError
from hmcore.fields.spec import FieldSpec, FilesPrior
from hmflow.cli import app

pytestmark = [requires_punq, requires_opm, pytest.mark.opm]

# PUNQ-S3's five layers as ../shared/punqs3/PRIOR.md describes them: porosity ranges 0.15-0.30
# in the channel layers 1, 3 and 5, 0.05-0.15 in the shaly layer 2, 0.10-0.20 in the mouth bar
# of layer 4 (mean the middle of the range, sd a quarter of it); channels 800 m wide at an
# azimuth of 110-170 degrees; log10(kh) = 0.77 + 9.02 phi with scatter.
LAYERS = [(1, 0.225, 0.04), (2, 0.10, 0.025), (3, 0.225, 0.04), (4, 0.15, 0.025),
          (5, 0.225, 0.04)]
ZONES = ",\n  ".join(f"{{ layers = [{k}, {k}], mean = {m}, std = {s} }}" for k, m, s in LAYERS)
PORO = f"""
[[parameters]]
name = "poro"
kind = "field"
keyword = "PORO"
low = 0.01
high = 0.35
[parameters.prior]
source = "geostatistical"
seed = 11
variogram = {{ model = "spherical", ranges = [2400.0, 800.0, 5.0], azimuth = [110.0, 170.0] }}
zones = [
  {ZONES}
]
"""
PERMX = """
[[parameters]]
name = "permx"
kind = "field"
keyword = "PERMX"
copies = ["PERMY"]
low = 0.1
high = 5000.0
[parameters.prior]
source = "relation"
from = "poro"
intercept = 0.77
slope = 9.02
scatter = 0.3
seed = 12
"""
SKIN = """
[[parameters]]
name = "skin"
kind = "skin"
low = -3.0
high = 10.0
"""
ENSEMBLE = """
[ensemble]
size = 100
localisation = "distance"
radius = 1500.0
"""
N_CELLS, N_ACTIVE = 19 * 28 * 5, 1761


def case_with(tmp_path: Path, *blocks: str) -> Path:
    return write_case_toml(tmp_path / "case.toml", name="fields", extra="\n".join(blocks))


def problems_of(case: Path) -> list:
    with pytest.raises(CaseError) as info:
        load_case(case)
    return info.value.problems


def one(problems, where: str, what: str):
    hits = [p for p in problems if re.search(where, p.where) and re.search(what, p.what)]
    assert len(hits) == 1, f"want one problem where~{where!r}, what~{what!r}; got {problems}"
    return hits[0]


def files_field(name: str, folder: str, keyword: str = "PORO", copies: str = "") -> str:
    return f"""
[[parameters]]
name = "{name}"
kind = "field"
keyword = "{keyword}"
{f'copies = ["{copies}"]' if copies else ""}
prior = {{ source = "files", folder = "{folder}" }}
"""


def write_members(folder: Path, n: int, values: int = N_CELLS, keyword: str = "PORO") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for m in range(n):
        (folder / f"poro_{m + 1}.grdecl").write_text(f"{keyword}\n{values}*0.2 /\n")
    return folder


def test_a_punqs3_case_with_porosity_and_permeability_fields_loads(tmp_path):
    case = load_case(case_with(tmp_path, PORO, PERMX, ENSEMBLE))
    assert [f.name for f in case.fields] == ["poro", "permx"]
    poro, permx = case.fields
    assert isinstance(poro, FieldSpec) and poro.keyword == "PORO" and poro.bounds == (0.01, 0.35)
    assert [z.layers for z in poro.prior.zones] == [(k, k) for k in range(1, 6)]
    assert permx.in_log and permx.written == ("PERMX", "PERMY") and permx.source_field == "poro"
    assert case.ensemble.size == 100 and case.ensemble.alphas == (7.0, 3.5, 1.75)
    assert case.ensemble.localisation == "distance" and case.ensemble.minimum == 50
    assert case.space.parameters == ()  # no scalar parameter: not the reference five


def test_a_case_without_an_ensemble_section_gets_the_defaults(tmp_path):
    case = load_case(case_with(tmp_path, PORO))
    assert case.ensemble.size == 100 and case.ensemble.weights == (4.0, 2.0, 1.0)
    assert load_case(write_case_toml(tmp_path / "plain.toml")).fields == ()


def test_a_case_mixing_scalars_and_fields_keeps_a_space_of_its_scalars(tmp_path):
    case = load_case(case_with(tmp_path, PORO, SKIN, PERMX))
    assert case.space.names == ["skin"] and case.space.dim == 1
    assert [f.name for f in case.fields] == ["poro", "permx"]


def test_check_prints_the_fields_and_the_ensemble(tmp_path):
    path = case_with(tmp_path, PORO, PERMX, SKIN, ENSEMBLE)
    out = CliRunner().invoke(app, ["check", "--case", str(path)],
                             env={"COLUMNS": "300", "NO_COLOR": "1"})
    assert out.exit_code == 0, out.output
    text = out.output
    poro = next(line for line in text.splitlines() if "field" in line and "poro" in line)
    assert "PORO" in poro and "geostatistical" in poro and "[0.01, 0.35]" in poro
    assert "layers 4-4: mean 0.15, sd 0.025" in text
    assert "spherical" in text and "110-170" in text
    permx = next(line for line in text.splitlines() if "field" in line and "permx" in line)
    assert "PERMX" in permx and "relation" in permx and "log10" in permx and "PERMY" in permx
    assert "0.77 + 9.02" in text
    ensemble = next(line for line in text.splitlines() if line.strip().startswith("ensemble"))
    assert "100 members" in ensemble and "4, 2, 1" in ensemble and "distance" in ensemble
    assert re.search(r"parameter\s+skin", text)


def test_a_files_prior_with_enough_members_loads_and_its_folder_is_resolved(tmp_path):
    write_members(tmp_path / "priors" / "poro", 3)
    write_members(tmp_path / "priors" / "permx", 3, values=N_ACTIVE, keyword="PERMX")
    case = load_case(case_with(tmp_path, files_field("poro", "priors/poro"),
                               files_field("permx", "priors/permx", keyword="PERMX",
                                           copies="PERMY"),  # the deck copies PERMX to PERMY
                               "[ensemble]\nsize = 3"))
    prior = case.fields[0].prior
    assert isinstance(prior, FilesPrior)
    assert Path(prior.folder) == (tmp_path / "priors" / "poro").resolve()


def test_bad_field_specifications_are_refused_all_at_once_with_file_and_key(tmp_path):
    write_members(tmp_path / "few", 3, keyword="PERMY")
    write_members(tmp_path / "short", 100, values=100)
    bad_keyword = PORO.replace('"poro"', '"a"').replace('"PORO"', '"PERMQ"')
    bad_layer = PORO.replace('"poro"', '"b"').replace("[5, 5]", "[6, 6]").replace(
        "seed = 11", "seed = 22").replace('keyword = "PORO"', 'keyword = "PERMX"').replace(
        "high = 0.35", "high = 5000.0")
    bad_bounds = PERMX.replace('"permx"', '"c"').replace("low = 0.1", "low = 9000.0")
    bad_from = PERMX.replace('"permx"', '"d"').replace('from = "poro"', 'from = "porosity"') \
        .replace('keyword = "PERMX"', 'keyword = "PERMZ"').replace('copies = ["PERMY"]', "") \
        .replace("seed = 12", "seed = 24")
    no_ntg = PORO.replace('"poro"', '"e"').replace('"PORO"', '"NTG"').replace(
        "seed = 11", "seed = 25")
    case = case_with(tmp_path, bad_keyword, bad_layer, bad_bounds, bad_from, no_ntg,
                     files_field("f", "few", keyword="PERMY"), files_field("g", "short"),
                     "[ensemble]\nmin_realisations = 10")
    problems = problems_of(case)
    file = re.escape(str(case))
    one(problems, rf"^{file} key 'parameters\.0\.keyword'$", r"one of .*PORO.*got 'PERMQ'")
    one(problems, rf"^{file} key 'parameters\.1\.prior\.zones\.4' \(layers 6-6\)$",
        r"layers must lie in 1\.\.5, got \[6, 6\]")
    one(problems, rf"^{file} key 'parameters\.2'$", r"low < high, got low=9000\.0, high=5000")
    one(problems, rf"^{file} key 'parameters\.3'$", r"from = 'porosity' names no field")
    one(problems, rf"^{file} key 'parameters\.4'$", r"the deck defines no NTG")
    few = one(problems, rf"^{file} key 'parameters\.5\.prior\.folder'",
              r"ensemble has 100 members but 3 file\(s\)")
    assert "few" in few.where
    short = [p for p in problems if re.search(rf"^{file} key 'parameters\.6\.prior' file ",
                                              p.where)]
    assert len(short) == 100 and "PORO has 100 values" in short[0].what
    assert f"{N_CELLS} cells, {N_ACTIVE} of them active" in short[0].what
    ens = one(problems, rf"^{file} key 'ensemble\.min_realisations'$", "not permitted")
    assert "did you mean 'min_realizations'" in ens.fix


def test_a_field_whose_keyword_the_deck_copies_to_another_is_refused_without_copies(tmp_path):
    """PUNQ-S3's GRID ends with COPY 'PERMX' 'PERMY', before the members' include: a PERMX field
    without ``copies = ["PERMY"]`` would leave every member the deck's (the truth's) PERMY."""
    case = case_with(tmp_path, PORO, PERMX.replace('copies = ["PERMY"]', ""), ENSEMBLE)
    problems = problems_of(case)
    p = one(problems, rf"^{re.escape(str(case))} key 'parameters\.1'$",
            r"PUNQS3\.DATA sets PERMY from PERMX in its GRID section \(COPY 'PERMX' 'PERMY'\)")
    assert 'copies = ["PERMY"]' in p.fix and len(problems) == 1
    # a field of PERMY's own is the other way out
    own = PERMX.replace('"permx"', '"permy"').replace('"PERMX"', '"PERMY"').replace(
        'copies = ["PERMY"]', "").replace("seed = 12", "seed = 13")
    assert load_case(case_with(tmp_path, PORO, PERMX.replace('copies = ["PERMY"]', ""), own,
                               ENSEMBLE)).fields[2].keyword == "PERMY"


def test_copies_are_followed_through_the_deck_in_order():
    """COPY PERMX PERMY then COPY PERMY PERMZ: both targets named at once for a PERMX field;
    a copy from a keyword no field writes, or onto one a field writes, is no problem."""
    from hmcore.fields.deck_edits import GridCopy, copy_problems

    permx = FieldSpec.model_validate({"name": "k", "kind": "field", "keyword": "PERMX",
                                      "prior": {"source": "files", "folder": "x"}})
    chain = [GridCopy("COPY", "PERMX", "PERMY"), GridCopy("COPYREG", "PERMY", "PERMZ"),
             GridCopy("COPY", "NTG", "PORO")]
    found = copy_problems([permx], chain, "D.DATA")
    assert [(p.where, p.what.split(" sets ")[1][:16]) for p in found] == [
        ("field 'k'", "PERMY from PERMX"), ("field 'k'", "PERMZ from PERMY")]
    with_y = permx.model_copy(update={"copies": ("PERMY",)})
    assert [p.what.split(" sets ")[1][:16] for p in copy_problems([with_y], chain, "D")] == [
        "PERMZ from PERMY"]
    assert copy_problems([with_y.model_copy(update={"copies": ("PERMY", "PERMZ")})], chain,
                         "D") == []


def test_a_deck_multiply_of_a_fields_keyword_is_named_and_a_neutral_one_is_not():
    """MULTIPLY PERMZ 0.1 before the members' include would be lost in every member."""
    from hmcore.fields.deck_edits import GridScaling, scaling_problems

    permz = FieldSpec.model_validate({"name": "kz", "kind": "field", "keyword": "PERMZ",
                                      "prior": {"source": "files", "folder": "x"}})
    edits = [GridScaling("MULTIPLY", "PERMZ", 0.1), GridScaling("ADD", "PERMZ", 0.0),
             GridScaling("MULTIREG", "PERMZ", 1.0), GridScaling("MULTIPLY", "PERMX", 2.0)]
    [p] = scaling_problems([permz], edits, "D.DATA")
    assert p.where == "field 'kz'" and "(MULTIPLY 'PERMZ' 0.1)" in p.what
    assert "remove the MULTIPLY of PERMZ" in p.fix
    # read from a deck by OPM's parser: GRID's records only, in order
    from opm.io.parser import Parser

    from hmcore.fields.deck_edits import grid_copies, grid_scalings

    deck = Parser().parse_string(
        "RUNSPEC\nDIMENS\n2 2 1 /\nGRID\nDX\n4*1 /\nDY\n4*1 /\nDZ\n4*1 /\nTOPS\n4*1 /\n"
        "PORO\n4*0.2 /\nPERMX\n4*100 /\nMULTIPLY\n'PERMX' 0.5 /\n/\nCOPY\nPERMX PERMZ /\n/\n"
        "ADD\nPORO 0.01 /\n/\nEDIT\nMULTIPLY\nPORV 2 /\n/\nPROPS\n")
    assert grid_scalings(deck) == [GridScaling("MULTIPLY", "PERMX", 0.5),
                                   GridScaling("ADD", "PORO", 0.01)]
    assert [(c.source, c.target) for c in grid_copies(deck)] == [("PERMX", "PERMZ")]


def test_an_unknown_key_inside_a_field_is_named_with_its_nearest_key(tmp_path):
    bad = PORO.replace("mean = 0.1,", "meen = 0.1,").replace("high = 0.35", "hihg = 0.35")
    problems = problems_of(case_with(tmp_path, bad, PERMX.replace("intercept", "intercpt")))
    file = re.escape(str(tmp_path / "case.toml"))
    assert "did you mean 'mean'" in one(
        problems, rf"^{file} key 'parameters\.0\.prior\.zones\.1\.meen'$", "not permitted").fix
    assert "did you mean 'high'" in one(
        problems, rf"^{file} key 'parameters\.0\.hihg'$", "not permitted").fix
    assert "did you mean 'intercept'" in one(
        problems, rf"^{file} key 'parameters\.1\.prior\.intercpt'$", "not permitted").fix


@pytest.mark.parametrize("section, key, what", [
    ("weights = [4.0, 0.0, 1.0]", "ensemble",
     r"weights must all be > 0, got \[4\.0, 0\.0, 1\.0\]"),
    ("size = 10\nmin_realizations = 20", "ensemble",
     r"min_realizations must lie in \[2, size = 10\], got 20"),
    ('localisation = "distance"', "ensemble", r"needs radius > 0"),
    ("size = 1", r"ensemble\.size", r"greater than or equal to 2"),
    ("size = 5.0", r"ensemble\.size", r"valid integer"),
])
def test_bad_ensemble_settings_are_refused_with_the_rule(tmp_path, section, key, what):
    problems = problems_of(case_with(tmp_path, PORO, f"[ensemble]\n{section}"))
    one(problems, rf"key '{key}'$", what)


def test_a_mistyped_kind_names_field_among_the_kinds(tmp_path):
    problems = problems_of(case_with(tmp_path, PORO.replace('kind = "field"', 'kind = "feild"')))
    assert "did you mean 'field'" in one(problems, r"key 'parameters\.0\.kind'$", "feild").fix


def test_a_campaign_refuses_a_case_of_fields_only_in_one_line(tmp_path):
    path = case_with(tmp_path, PORO, PERMX)
    out = CliRunner().invoke(app, ["run", "--case", str(path), "--agent", "random", "--budget",
                                   "1", "--storage", str(tmp_path / "store")],
                             env={"COLUMNS": "300", "NO_COLOR": "1"})
    assert out.exit_code == 2, out.output
    text = " ".join(out.output.split())
    assert "field parameters only (poro, permx)" in text and "no scalar parameter" in text
    assert not (tmp_path / "store").exists()


def test_the_deck_is_parsed_once_for_the_fields(tmp_path, monkeypatch):
    from hmcore.eclipse import deck_info

    calls = []
    parse = deck_info._parse
    monkeypatch.setattr(deck_info, "_parse", lambda path: calls.append(path) or parse(path))
    load_case(case_with(tmp_path, PORO, PERMX))
    assert calls == [PUNQ_DECK.resolve()]
