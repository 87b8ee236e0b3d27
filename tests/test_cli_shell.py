"""The command line is a thin shell: importing it changes nothing in the process (Prefect's
environment is set when a command runs), its input rules are the flows' own, and `hide`
refuses a bad request before anything is written. No simulator runs here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from flows.inputs import input_problems
from flows.runners import RUNNERS
from hmcore.calibration.registry import METHODS

OWN = ("PREFECT_SERVER_ANALYTICS_ENABLED", "DO_NOT_TRACK", "PREFECT_LOGGING_LEVEL",
       "PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL")
"""The variables hmflow sets for Prefect when a command runs (unless the user set them)."""

PROBE = """
import json, os, sys
before = dict(os.environ)
{statement}
after = dict(os.environ)
print(json.dumps({{"changed": sorted(k for k in set(before) | set(after)
                                     if before.get(k) != after.get(k)),
                   "prefect": "prefect" in sys.modules,
                   "console_level": after.get("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL"),
                   "dnt": after.get("DO_NOT_TRACK")}}))
"""


def _probe(statement: str, tmp_path: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in OWN}
    p = subprocess.run([sys.executable, "-c", PROBE.format(statement=statement)], env=env,
                       cwd=tmp_path, capture_output=True, text=True, timeout=120, check=False)
    assert p.returncode == 0, p.stdout + p.stderr
    return json.loads(p.stdout.strip().splitlines()[-1])


def test_importing_the_cli_changes_no_environment_variable(tmp_path):
    got = _probe("import hmflow.cli", tmp_path)
    assert got["changed"] == [] and not any(k.startswith("PREFECT_") for k in got["changed"])
    assert not got["prefect"]  # nor imports Prefect (it reads its settings on import)


def test_a_command_run_sets_prefects_terminal_defaults(tmp_path):
    got = _probe("from typer.testing import CliRunner\nfrom hmflow.cli import app\n"
                 "assert CliRunner().invoke(app, ['check', '--help']).exit_code == 0",
                 tmp_path)
    assert {"DO_NOT_TRACK", "PREFECT_SERVER_ANALYTICS_ENABLED"} <= set(got["changed"])
    assert got["console_level"] == "WARNING" and got["dnt"] == "1"
    assert not got["prefect"]


def test_python_m_hmflow_cli_is_the_hmflow_command(tmp_path):
    p = subprocess.run([sys.executable, "-m", "hmflow.cli", "--help"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120, check=False,
                       env={**os.environ, "COLUMNS": "200"})
    assert p.returncode == 0, p.stderr
    for command in ("init", "check", "evaluate", "run", "report", "tables", "bench", "deploy",
                    "diagnose", "hide", "reveal"):
        assert f" {command} " in p.stdout, command


def _invoke(args: list[str]):
    from hmflow.cli import app

    out = CliRunner().invoke(app, args, env={"COLUMNS": "300", "NO_COLOR": "1"})
    return out, " ".join(out.output.split())


def test_the_command_line_and_the_flows_check_one_rule_spelled_their_way(restore_env):
    """`--task-runner nope` is refused by the flows' own rule, named as the option."""
    flow_says = input_problems(task_runner="nope")
    assert flow_says == [f"task_runner must be one of {list(RUNNERS)}, got 'nope'"]
    out, text = _invoke(["diagnose", "--task-runner", "nope"])
    assert out.exit_code == 2 and "Traceback" not in out.output
    assert f"--task-runner must be one of {list(RUNNERS)}, got 'nope'" in text
    assert input_problems("nope") == [f"agent must be one of {list(METHODS)}, got 'nope'"]
    assert input_problems("sac-paper", 7, 2) == [
        ("agent sac-paper, budget 7, workers 2: sac-paper steps its 2 env copies together: the "
         "budget 7 must be a multiple of the workers 2 (e.g. 6)")]


@pytest.mark.parametrize("args, says", [
    (["--kind", "nope"], "--kind 'nope': unknown"),
    (["--kind", "partial_fault", "--candidate", "well_skin:PROD2"], "not both"),
    (["--kind", "well_skin", "--candidate", "layer_permeability:3"], "is not of --kind"),
    (["--value", "2"], "--value needs --candidate"),
    (["--set", "skin=3"], "apply to --deck cases"),
    (["--deck", "no/such.DATA"], "no such file"),
])
def test_hide_refuses_a_bad_request_before_writing_anything(args, says, tmp_path, restore_env):
    out, text = _invoke(["hide", "--out", str(tmp_path / "case"), *args])
    assert out.exit_code == 2 and says in text and "Traceback" not in out.output, out.output
    assert not (tmp_path / "case").exists()


def test_hide_leaves_nothing_behind_when_the_effect_cannot_be_made(tmp_path, restore_env):
    """The synthetic base deck is written, then the candidate is not among its own: the
    folder goes again (no simulation was started)."""
    out, text = _invoke(["hide", "--out", str(tmp_path / "case"), "--candidate",
                         "well_skin:NOSUCHWELL", "--value", "2"])
    assert out.exit_code == 2 and "offers no candidate 'well_skin:NOSUCHWELL'" in text, out.output
    assert not (tmp_path / "case").exists()


def test_reveal_names_a_missing_file(tmp_path, restore_env):
    out, text = _invoke(["reveal", "--hidden", str(tmp_path / "h.json"), "--diagnosis",
                         str(tmp_path / "d.json")])
    assert out.exit_code == 2
    assert f"--hidden {tmp_path / 'h.json'}: no such file" in text
    assert f"--diagnosis {tmp_path / 'd.json'}: no such file" in text
