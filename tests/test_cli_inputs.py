"""`--set NAME=VALUE` as users mistype it: every bad value refused with exit 2 and a line that
names the item, before anything runs (no simulator, no Prefect)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import typer
from hypothesis import given, settings
from hypothesis import strategies as st

from hmflow.cli.common import parse_sets

NAMES = ["poro_mult", "permx_mult", "permy_mult", "permz_mult", "skin"]


@pytest.mark.parametrize("item, says", [
    ("skin=nan", "not a finite number"), ("skin=inf", "not a finite number"),
    ("skin=-inf", "not a finite number"), ("skin=1e309", "not a finite number"),
    ("skin=abc", "is not a number"), ("skin", "expected NAME=VALUE"),
    ("skn=5", "did you mean 'skin'"), ("porosity=1", "unknown parameter 'porosity'"),
])
def test_a_bad_set_value_is_refused_with_its_item(item, says, capsys):
    with pytest.raises(typer.Exit) as exit_:
        parse_sets([item], NAMES)
    assert exit_.value.exit_code == 2
    err = capsys.readouterr().err
    assert says in " ".join(err.split()) and repr(item)[1:-1] in err


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=30))
def test_any_value_text_is_a_finite_number_or_refused(value):
    try:
        got = parse_sets([f"skin={value}"], NAMES)
    except typer.Exit as exc:
        assert exc.exit_code == 2
    else:
        assert math.isfinite(got["skin"]) and got["skin"] == float(value)


@pytest.mark.parametrize("command", [["run", "--budget", "1"], ["report"], ["diagnose"],
                                     ["tables"]])
@pytest.mark.parametrize("name", ["", "../S", "a/b", ".hidden"])
def test_a_bad_campaign_name_is_refused_before_anything_starts(command, name, tmp_path):
    from typer.testing import CliRunner

    from hmflow.cli import app

    out = CliRunner().invoke(app, [*command, "--campaign", name, "--storage", str(tmp_path)],
                             env={"COLUMNS": "200"})
    assert out.exit_code == 2, out.output
    assert "invalid campaign name" in " ".join(out.output.split()) and "Traceback" not in out.output
    assert list(tmp_path.iterdir()) == []  # nothing written, nothing started


def _invoke(args):
    from typer.testing import CliRunner

    from hmflow.cli import app

    out = CliRunner().invoke(app, args, env={"COLUMNS": "300", "NO_COLOR": "1"})
    return out, " ".join(out.output.split())


@pytest.mark.parametrize("command, option", [
    (["evaluate", "--case", "synthetic", "--set", "skin=5"], "--out"),
    (["run", "--budget", "1", "--agent", "random"], "--storage"),
    (["bench", "--budget", "1", "--methods", "random", "--seeds", "1"], "--storage"),
])
def test_a_folder_option_naming_a_file_is_one_line_not_a_traceback(command, option, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for path in (a_file, a_file / "below"):
        out, text = _invoke([*command, option, str(path)])
        assert out.exit_code == 2, out.output
        assert f"{option} {path}" in text and "Traceback" not in out.output
    assert a_file.read_text() == "x"


@pytest.mark.parametrize("case, says", [
    ("binary", "not a text file in UTF-8"), ("a\x01b.toml", "case file not found"),
    ("~nosuchuser/x.toml", "cannot be expanded"),
])
def test_a_case_path_users_mistype_is_one_problem(case, says, tmp_path):
    if case == "binary":
        case = str(tmp_path / "binary.toml")
        Path(case).write_bytes(bytes(range(256)))
    out, text = _invoke(["check", "--case", case])
    assert out.exit_code == 2 and says in text and "Traceback" not in out.output, out.output


@pytest.mark.parametrize("args, says", [
    (["--fork", "new"], "--fork needs --campaign"),
    (["--campaign", "old", "--fork", "old"], "give a new campaign name"),
    (["--campaign", "old", "--fork", "new"], "there is no campaign 'old'"),
    (["--campaign", "old", "--fork", "../x"], "invalid campaign name"),
])
def test_fork_is_checked_before_prefect_starts(args, says, tmp_path):
    out, text = _invoke(["run", "--budget", "1", "--agent", "random", "--storage",
                         str(tmp_path), *args])
    assert out.exit_code == 2 and says in text and "Traceback" not in out.output, out.output
    assert list(tmp_path.iterdir()) == []


def test_a_linked_campaign_folder_is_refused_before_prefect_starts(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "c").symlink_to(outside, target_is_directory=True)
    out, text = _invoke(["run", "--budget", "1", "--agent", "random", "--campaign", "c",
                         "--storage", str(tmp_path / "store")])
    assert out.exit_code == 2 and "symbolic link" in text, out.output
    assert list(outside.iterdir()) == []


def test_the_help_lists_every_kind_and_generator():
    """``--kinds`` and ``hide --kind`` spell their choices out (so ``--help`` does not import
    the diagnosis): every family and every generator is there, and nothing else."""
    from hmcore.diagnosis.candidate import DEFAULT_KINDS, KINDS
    from hmcore.scenarios.generators import GENERATORS
    from hmflow.cli.common import GENERATORS_HELP, KINDS_HELP

    assert KINDS_HELP.split(": ", 1)[1].split(", ") == list(KINDS)
    # "all but the last two"
    assert list(KINDS[-2:]) == [k for k in KINDS if k not in DEFAULT_KINDS]
    assert sorted(GENERATORS_HELP.split(", ")) == sorted(GENERATORS)
