"""Bad values given to a flow run (as from the UI's run form or a deployment): the run ends
Failed before any simulation with one clear message naming what is wrong, and its log holds
no traceback (real Prefect: the session's server, conftest.prefect_api)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import cli_env, requires_opm, requires_punq, write_case_toml

SCRIPT = """
import sys
from flows.campaign import campaign_flow
state = campaign_flow(case=sys.argv[1], agent=sys.argv[2], budget=int(sys.argv[3]),
                      workers=2, storage=sys.argv[4], task_runner=sys.argv[5],
                      return_state=True)
print("STATE", state.type.value, "|", state.message)
"""


@pytest.mark.parametrize("case, agent, budget, runner, expected", [
    ("{tmp}/nowhere.toml", "random", 4, "threads", "nowhere.toml"),
    ("synthetic", "esmda", 3, "threads", "esmda needs an ensemble"),
    # a typed parameter (a choice in the UI's form) is refused by Prefect's own validation
    ("synthetic", "random", 4, "spark", "task_runner: Input should be 'threads', 'dask', 'slurm', 'pbs' or 'lsf'"),
    ("synthetic", "random", 0, "threads", "budget: Input should be greater than or equal to 1"),
])
def test_a_bad_value_fails_the_run_with_one_clear_line(tmp_path, case, agent, budget, runner,
                                                        expected, prefect_api):
    store = tmp_path / "store"
    proc = subprocess.run([sys.executable, "-c", SCRIPT, case.format(tmp=tmp_path), agent,
                           str(budget), str(store), runner], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path, env=cli_env(prefect_api))
    out = proc.stdout + proc.stderr
    line = [ln for ln in out.splitlines() if ln.startswith("STATE ")]
    assert line and line[0].startswith("STATE FAILED |"), out
    assert expected in " ".join(out.split()), out
    assert "Traceback" not in out, out
    assert not (store / "synthetic-esmda-seed0" / "runs").exists()
    assert not list(store.glob("*/runs/*")) if store.exists() else True  # nothing simulated


@requires_punq
@requires_opm
def test_a_case_of_fields_only_fails_the_flow_run_before_any_simulation(tmp_path, prefect_api):
    """From the UI or the API as from the command line: a calibration needs scalar
    parameters; a case of field parameters only (the ensemble smoother's) is refused in one
    line and nothing is simulated (flows.inputs.scalar_problems)."""
    from test_case_fields import PERMX, PORO

    case = write_case_toml(tmp_path / "case.toml", name="fields", extra=PORO + PERMX)
    store = tmp_path / "store"
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(case), "random", "2", str(store),
                           "threads"], capture_output=True, text=True, timeout=300,
                          cwd=tmp_path, env=cli_env(prefect_api))
    out = proc.stdout + proc.stderr
    line = [ln for ln in out.splitlines() if ln.startswith("STATE ")]
    assert line and line[0].startswith("STATE FAILED |"), out
    assert "field parameters only (poro, permx)" in " ".join(out.split()), out
    assert "Traceback" not in out, out
    assert not list(store.glob("*/runs/*")) if store.exists() else True  # nothing simulated
