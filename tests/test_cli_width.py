"""The command line at 80 columns in a pipe (CI, a narrow window): `--help` in plain words
(no typer `<bool>`, no docstring lines ragged at the width), the default campaign name stated
by the rule that makes it, paths on lines of their own (never broken), table columns wrapped
instead of cut, `hmflow evaluate` in the words of a least-squares user, and an unknown
`--campaign` answered with the campaigns the store holds. `hmflow report` at 80 columns is
tested on the campaign that tests/test_cli_terminal.py runs anyway."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from hmcore.calibration.registry import DEFAULT_AGENT, default_campaign_name

ROOT = Path(__file__).resolve().parents[1]
TYPER_VALUE = re.compile(r"<(bool|str|int|float|path|list|choice)\b")
"""What typer shows after an option for its value's type (``<bool>``, ``<int range>``...)."""


def piped(*args: str, cwd: Path, timeout: int = 300) -> subprocess.CompletedProcess:
    """`hmflow ARGS` in a subprocess writing to pipes, at 80 columns."""
    return subprocess.run([sys.executable, "-m", "hmflow.cli", *args], cwd=cwd,
                          env={**os.environ, "COLUMNS": "80"}, capture_output=True, text=True,
                          timeout=timeout, check=False)


def words(text: str) -> str:
    """The text of a rich panel with its box and runs of white space as one space."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", text).split())


def test_run_help_at_80_columns_states_the_default_campaign_name_in_plain_words():
    from hmflow.cli import app

    out = CliRunner().invoke(app, ["run", "--help"], env={"COLUMNS": "80"})  # not a terminal
    assert out.exit_code == 0, out.output
    lines = out.stdout.splitlines()
    assert max(map(len, lines)) <= 80, [line for line in lines if len(line) > 80]
    assert not TYPER_VALUE.search(out.stdout), out.stdout
    assert re.search(r"--verbose\s{2,}Also show", out.stdout)          # a flag: no value shown
    assert re.search(r"--budget\s+INTEGER", out.stdout)                # a value: a plain word
    said = words(out.stdout)
    # the rule, and the name it makes with the defaults (the method's version included)
    name = default_campaign_name("synthetic", DEFAULT_AGENT, 0)
    assert "Default: CASE-AGENT-vN-seedS (the case's name, --agent, the method's version N" in said
    assert f"with the defaults: {name}. Printed when the run starts and ends" in said


def test_a_commands_text_is_rewrapped_to_the_width_not_ragged():
    """`deploy --help`: a docstring of several paragraphs, each wrapped at 80 columns as one
    (typer keeps the source's line breaks after the first paragraph: a line of 90 characters
    became one of 80 and one of 10)."""
    from hmflow.cli import app

    out = CliRunner().invoke(app, ["deploy", "--help"], env={"COLUMNS": "80"})
    assert out.exit_code == 0, out.output
    head = out.output[:out.output.index("╭")]
    paragraphs = [[line for line in p.splitlines() if line.strip()]
                  for p in re.split(r"\n\s*\n", head) if p.strip()]
    assert len(paragraphs) >= 3, head                      # usage, summary, the rest
    for lines in paragraphs:
        short = [line for line in lines[:-1] if len(line.rstrip()) < 60]
        assert not short, head                             # only a paragraph's last line is short
    assert not TYPER_VALUE.search(out.output), out.output


def test_the_readme_gives_the_default_campaign_name_of_make_run():
    readme = (ROOT / "README.md").read_text()
    name = default_campaign_name("synthetic", DEFAULT_AGENT, 0)
    assert f"stores the campaign `{name}`" in readme
    assert f"hmflow report --campaign {name}\n" in readme
    assert "CASE-AGENT-vN-seedS" in readme


def test_an_unknown_campaign_names_the_nearest_and_what_the_store_holds(tmp_path):
    """The issue's case: the name before the method's version was in it. Reference runs'
    folders are no campaigns to offer; an empty or missing store says so."""
    from hmflow.cli import app

    store = tmp_path / "store"
    stored = default_campaign_name("synthetic", DEFAULT_AGENT, 0)
    for name, settings in ((stored, {"reference": f"{stored}-reference"}),
                           (f"{stored}-reference", {}), ("punqs3-cmaes-seed1", {})):
        (store / name).mkdir(parents=True)
        (store / name / "campaign.json").write_text(json.dumps(settings))
    runner = CliRunner()
    for command in ("report", "tables"):
        out = runner.invoke(app, [command, "--storage", str(store), "--campaign",
                                  "synthetic-lm-seed0"], env={"COLUMNS": "80"})
        said = " ".join(out.stderr.split())
        assert out.exit_code == 2, out.output
        assert f"no campaign 'synthetic-lm-seed0' in {store}. Did you mean '{stored}'?" in said
        assert said.endswith(f"It holds: punqs3-cmaes-seed1, {stored}"), said
        assert out.stderr.count("\n") == 1, out.stderr      # one line, its path unbroken
    far = runner.invoke(app, ["report", "--storage", str(store), "--campaign", "x"])
    assert "Did you mean" not in far.stderr and f"in {store}. It holds:" in far.stderr
    (tmp_path / "empty").mkdir()
    for where, held in ((tmp_path / "empty", "it holds no campaign"),
                        (tmp_path / "none", "it does not exist")):
        out = runner.invoke(app, ["report", "--storage", str(where), "--campaign", "x"])
        assert out.exit_code == 2 and held in out.stderr, out.stderr


def test_tables_wrap_or_say_what_they_leave_out_instead_of_cutting(monkeypatch):
    """PUNQ-S3's tables at 80 columns: a reason a record is left out (``shut_in_observed``)
    was cut to 'shut_in_obse…' and the injection columns to 'water_…'; now the reason wraps
    at its spaces and a column with no record at any well is left out, saying so."""
    from rich.console import Console

    import hmcore.reporting.paper_tables as paper
    from hmflow.cli import common

    wells = ("PRO-1", "PRO-4", "PRO-5", "PRO-11", "PRO-12", "PRO-15")
    tables = {
        "categories": pd.DataFrame({"category": ["oil", "macro (oil, water, gas, bhp)"],
                                    "N": [240, 960], "NMSE": [0.0, 0.0615],
                                    "R2": [1.0, 0.6841], "C_match": [100.0, 94.21]}),
        "wells": pd.DataFrame({"well": list(wells), **{c: [97.45] * 6 for c in (
            "oil", "water", "gas", "bhp", "gor", "wct")}, "water_inj": [None] * 6,
            "gas_inj": [float("nan")] * 6}),
        "ratios": pd.DataFrame({"ratio": ["gor"] * 6, "well": list(wells), "N": [28] * 6,
                                "excluded": [12] * 6, "why": ["shut_in_observed 12"] * 6,
                                "NMSE": [0.0243] * 6, "R2": [0.8313] * 6,
                                "C_match": [97.62] * 6})}
    monkeypatch.setattr(paper, "paper_tables", lambda metrics: tables)
    console = Console(width=80, file=io.StringIO(), record=True)
    monkeypatch.setattr(common, "console", console)
    common.print_tables({}, "Best case:")
    text = console.export_text()
    assert "…" not in text, text
    assert max(map(len, text.splitlines())) <= 80
    assert "(water_inj, gas_inj: no record at any well, left out)" in text
    assert "water_inj" not in text.split("(water_inj")[0]               # not a column
    rows = [line for line in text.splitlines() if "│ gor" in line]
    assert len(rows) == 6 and all("shut in" in r for r in rows), text   # wrapped, not cut
    assert text.count("observed 12") == 6


@pytest.mark.opm
def test_evaluate_at_80_columns_speaks_least_squares_and_breaks_no_path(tmp_path, small_case):
    """One real OPM run of the small synthetic case (conftest.small_case), piped at 80 columns:
    the call valid / penalised / failed with E and the likelihood, no reinforcement-learning
    words, each path written on a line of its own."""
    out_dir = tmp_path / "a-folder-with-a-long-name-so-that-the-path-is-longer-than-80-columns"
    run = piped("evaluate", "--case", str(small_case), "--set", "skin=5", "--out", str(out_dir),
                cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    text = run.stdout
    assert "reward" not in text and "status COMPLETE" not in text, text
    assert re.match(r"(valid|penalised): E = \d\.\d{6}, likelihood \(chi2/n\) = \d", text), text
    assert "(the case's objective)" in text and "simulator" in text
    assert "…" not in text, text
    written = [line.removeprefix("wrote ") for line in text.splitlines()
               if line.startswith("wrote ")]
    assert written == [str(out_dir / "metrics.json"), str(out_dir / "responses.parquet")]
    assert all(Path(p).is_file() and len(p) > 80 for p in written)  # longer than the width
    others = [line for line in text.splitlines() if not line.startswith("wrote ")]
    assert max(map(len, others)) <= 80, others
    doc = json.loads((out_dir / "metrics.json").read_text())
    assert f"E = {doc['misfit']['E']:.6f}" in text
