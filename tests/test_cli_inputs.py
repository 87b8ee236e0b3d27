"""`--set NAME=VALUE` as users mistype it: every bad value refused with exit 2 and a line that
names the item, before anything runs (no simulator, no Prefect)."""

from __future__ import annotations

import math

import pytest
import typer
from hypothesis import given, settings
from hypothesis import strategies as st

from hmflow.cli import parse_sets

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
