"""Bad values given to a flow run (as from the UI's run form or a deployment): the run ends
Failed before any simulation with one clear message naming what is wrong, and its log holds
no traceback (real Prefect: the session's server, conftest.prefect_api)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import cli_env

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
    ("synthetic", "random", 4, "spark", "task_runner: Input should be 'threads' or 'dask'"),
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
