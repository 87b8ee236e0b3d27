"""Simulator backends and failure handling.

Both backends are real: OpmFlow (pip opm-simulators, one subprocess per run) and
CommandLineSimulator with Debian's ``flow`` executable. Failures must come back as
SimulationError with the right reason; evaluate() must record them as FAIL and never raise.
Fake simulators are used only for the logic around the simulator.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from conftest import PUNQ_DECK, TRUTH_VALUES, copy_punq_deck
from hmcore.model.run_deck import prepare_run_deck
from hmcore.errors import FailureKind, SimulationError
from hmcore.scoring.evaluation import Status, evaluate, score_responses
from hmcore.model.parameters import ParameterSpace
from hmcore.simulation.responses import INJECTION, QUANTITIES, last_time, read_responses
from hmcore.simulation.simulator import (CommandLineSimulator, OpmFlow, SimulationResult, make_simulator,
                                         run_in_own_group)

# Tests that need the PUNQ-S3 data get it through fixtures that skip when it is absent;
# tests marked opm are skipped when OPM is not installed (conftest).

FLOW = shutil.which("flow")
requires_flow_exe = pytest.mark.skipif(FLOW is None, reason="no 'flow' executable on PATH "
                                       "(Debian package opm-simulators)")


@pytest.fixture
def truth_deck(tmp_path, punq_info) -> Path:
    """A per-run copy of the truth deck (INCLUDE paths absolute) in its own run dir."""
    return prepare_run_deck(PUNQ_DECK, {}, ParameterSpace.reference(), tmp_path / "run", punq_info)


@pytest.fixture
def broken_deck(tmp_path, punq_dir) -> Path:
    """A deck OPM cannot parse (DIMENS item 2 is not an integer)."""
    deck = copy_punq_deck(tmp_path / "broken")
    deck.write_text(deck.read_text().replace("   19    28      5 /", "   19  abc  5 /"))
    return deck


def write_short_deck(dest: Path) -> Path:
    """The PUNQ-S3 deck with its schedule cut after 1 Jan 1969 (day 731): a ~1 s real run."""
    deck = copy_punq_deck(dest)
    text = deck.read_text()
    cut = text.index("DATES              \n1  'JAN'  1970")
    deck.write_text(text[:cut] + "END\n")
    return deck


def bhp_table(summary: Path):
    r = read_responses(summary)
    return r[r.quantity == "WBHP"].set_index(["well", "days"])["value"]


# ----------------------------------------------------------------------------- real runs
@pytest.mark.opm
def test_opm_flow_runs_punq_truth(truth_run, punq_info):
    assert truth_run.backend == "opm-flow-python"
    assert truth_run.summary_path.name == "PUNQS3.SMSPEC" and truth_run.summary_path.is_file()
    assert (truth_run.run_dir / "PUNQS3.UNSMRY").is_file()
    assert truth_run.wall_time_s > 0
    # its peak resident memory, measured (about 105 MB on the machines this was written on)
    assert 30e6 < truth_run.peak_rss_bytes < 2e9
    assert last_time(truth_run.summary_path) == pytest.approx(punq_info.end_days)  # 6025 d
    r = read_responses(truth_run.summary_path)
    assert set(r.well) == set(punq_info.wells)
    assert set(r.quantity) == set(QUANTITIES) - set(INJECTION)  # PUNQ-S3 has no injector
    oil = r[r.quantity == "WOPR"].set_index(["well", "days"])["value"]
    # the schedule's rate targets (WELTARG ORAT): 100 sm3/d on day 1, 200 in month 4-6,
    # 0 while shut in during 1968-1970, 150 from 1971
    for well in punq_info.wells:
        assert oil[(well, 1.01)] == pytest.approx(100.0, rel=1e-4)
        assert oil[(well, 120.0)] == pytest.approx(200.0, rel=1e-4)
        assert oil[(well, 731.0)] == pytest.approx(0.0, abs=1e-6)
        assert oil[(well, 1642.0)] == pytest.approx(150.0, rel=1e-4)
    bhp = bhp_table(truth_run.summary_path)
    flowing = bhp[bhp.index.get_level_values("days") >= 1.0]
    assert (flowing >= 120.0 - 1e-6).all() and (flowing < 300.0).all()  # BHP floor 120 bar


@pytest.mark.opm
@requires_flow_exe
def test_command_line_flow_gives_the_same_bhp(truth_deck, truth_run, punq_info):
    sim = make_simulator(f"{FLOW} {{deck}} --output-dir={{run_dir}} --enable-terminal-output=false",
                         timeout_s=600)
    assert isinstance(sim, CommandLineSimulator)
    res = sim.run(truth_deck, truth_deck.parent)
    assert res.backend.startswith("command-line:")
    assert res.summary_path == truth_deck.parent / "PUNQS3.SMSPEC"
    a, b = bhp_table(res.summary_path), bhp_table(truth_run.summary_path)
    common = a.index.intersection(b.index)
    # every well at every report step (the first, day 0, has no summary record)
    assert len(common) == len(b) == 6 * (len(punq_info.report_days) - 1)
    diff = (a[common] - b[common]).abs()
    assert diff.max() < 4.0, diff.sort_values().tail()  # two OPM versions (2022.10 vs 2026.4)
    assert diff.mean() < 1.0


@pytest.mark.opm
@requires_flow_exe
@pytest.mark.skipif(shutil.which("mpirun") is None, reason="no mpirun on PATH")
def test_mpi_processes_per_run_through_the_command_template(truth_deck, truth_run, tmp_path):
    """``processes = 2`` with a command that starts them: Debian's flow (built with MPI) runs
    the deck on 2 processes and gives the single-process answer."""
    run_deck = tmp_path / "mpi" / truth_deck.name
    shutil.copytree(truth_deck.parent, run_deck.parent,
                    ignore=shutil.ignore_patterns("*.SMSPEC", "*.UNSMRY", "*.UNRST", "*.EGRID",
                                                  "*.INIT", "*.PRT", "*.DBG", "*.RSM"))
    sim = make_simulator(f"mpirun --allow-run-as-root --oversubscribe -np {{processes}} {FLOW} "
                         "{deck} --output-dir={run_dir} --enable-terminal-output=false "
                         "--threads-per-process={threads}", timeout_s=600, processes=2)
    assert sim.command(run_deck, run_deck.parent)[:6] == [
        "mpirun", "--allow-run-as-root", "--oversubscribe", "-np", "2", FLOW]
    res = sim.run(run_deck, run_deck.parent)
    prt = (run_deck.parent / "PUNQS3.PRT").read_text(errors="replace")
    assert re.search(r"Load balancing distributes \d+ active cells on 2 processes", prt)
    a, b = bhp_table(res.summary_path), bhp_table(truth_run.summary_path)
    common = a.index.intersection(b.index)
    assert len(common) == len(b)
    assert (a[common] - b[common]).abs().max() < 4.0  # 2022.10 on 2 processes vs 2026.4


def test_mpi_processes_with_the_built_in_opm_flow_are_refused(tmp_path):
    from hmcore.cases import load_case
    from hmcore.errors import CaseError
    from conftest import write_case_toml

    path = write_case_toml(tmp_path / "c.toml", extra="[simulator]\nprocesses = 2\n")
    with pytest.raises(CaseError) as info:
        load_case(path)
    text = str(info.value)
    assert "simulator.processes" in text and "without MPI" in text and "mpirun -np" in text


# ----------------------------------------------------------------------------- failures
@pytest.mark.opm
def test_opm_flow_parse_error(broken_deck, tmp_path):
    with pytest.raises(SimulationError) as info:
        OpmFlow(timeout_s=120).run(broken_deck, tmp_path / "run")
    err = info.value
    assert err.reason in ("parse_error", "crash")
    assert err.run_dir == tmp_path / "run"
    assert err.log_tail.strip(), "the log tail must say something"
    assert "exited with code" in err.message
    assert (tmp_path / "run" / "simulator.log").is_file()
    assert "log tail" in str(err)


@pytest.mark.opm
@requires_flow_exe
def test_command_line_flow_parse_error(broken_deck, tmp_path):
    with pytest.raises(SimulationError) as info:
        CommandLineSimulator(timeout_s=120).run(broken_deck, tmp_path / "run")
    assert info.value.reason in ("parse_error", "crash")
    assert "exited with code" in info.value.message


# regression: the log tail used to hold only stderr, without OPM's parser message (stdout)
@pytest.mark.opm
@pytest.mark.parametrize("backend", ["opm", pytest.param("flow", marks=requires_flow_exe)])
def test_parse_error_log_tail_names_the_problem(backend, broken_deck, tmp_path):
    sim = OpmFlow(timeout_s=120) if backend == "opm" else CommandLineSimulator(timeout_s=120)
    with pytest.raises(SimulationError) as info:
        sim.run(broken_deck, tmp_path / "run")
    assert "DIMENS" in info.value.log_tail and "abc" in info.value.log_tail


@pytest.mark.opm
@pytest.mark.parametrize("backend", ["opm", pytest.param("flow", marks=requires_flow_exe)])
def test_timeout(backend, truth_deck):
    sim = OpmFlow(timeout_s=0.5) if backend == "opm" else CommandLineSimulator(timeout_s=0.5)
    start = time.perf_counter()
    with pytest.raises(SimulationError) as info:
        sim.run(truth_deck, truth_deck.parent)
    assert info.value.reason == "timeout"
    assert "timeout_s" in info.value.message
    assert time.perf_counter() - start < 10.0  # killed, not waited for


def test_timeout_message_states_the_limit(tmp_path):
    sim = CommandLineSimulator(template="sh -c 'sleep 5' {deck}", timeout_s=0.5)
    with pytest.raises(SimulationError) as info:
        sim.run(tmp_path / "CASE.DATA", tmp_path / "run")
    assert info.value.reason == "timeout"
    assert "0.5 s" in info.value.message


def test_missing_executable_in_template(tmp_path):
    sim = CommandLineSimulator(template="no-such-simulator-xyz {deck} --out={run_dir}")
    with pytest.raises(SimulationError) as info:
        sim.run(tmp_path / "CASE.DATA", tmp_path / "run")
    err = info.value
    assert err.reason == "crash"
    assert "no-such-simulator-xyz" in err.message and "template" in err.message


# regression: a PermissionError used to escape as a raw OSError
def test_non_executable_in_template_is_a_simulation_error(tmp_path):
    sim = CommandLineSimulator(template=f"{tmp_path} {{deck}}")  # a directory: not executable
    with pytest.raises(SimulationError) as info:
        sim.run(tmp_path / "CASE.DATA", tmp_path / "run")
    assert info.value.reason == "crash" and str(tmp_path) in info.value.message


def test_command_template_placeholders(tmp_path):
    sim = CommandLineSimulator(template="sim {deck} --out={run_dir} --case {case}")
    cmd = sim.command(tmp_path / "PUNQS3.DATA", tmp_path / "run")
    assert cmd == ["sim", str(tmp_path / "PUNQS3.DATA"), f"--out={tmp_path / 'run'}", "--case",
                   "PUNQS3"]


# Exit-code rules, with a tiny shell script standing in for a command-line simulator.
@pytest.mark.parametrize("script, reason", [
    ("echo Unknown keyword FOO >&2; exit 1", "crash"),
    ("echo segmentation fault >&2; exit 139", "crash"),
    ("echo going down >&2; kill -9 $$", "killed"),  # killed by a signal (e.g. out of memory)
    ("echo all done >&2; exit 0", "no_output"),  # finished but wrote no summary
])
def test_exit_codes_map_to_reasons(tmp_path, script, reason):
    sim = CommandLineSimulator(template=f"sh -c '{script}' {{deck}}", timeout_s=30)
    with pytest.raises(SimulationError) as info:
        sim.run(tmp_path / "CASE.DATA", tmp_path / "run")
    err = info.value
    assert err.reason == reason
    assert script.split("echo ")[1].split(" >&2")[0] in err.log_tail  # stderr is kept
    assert err.run_dir == tmp_path / "run"
    if reason == "crash":
        assert f"exited with code {script.rsplit('exit ', 1)[1]}" in err.message


def test_summary_found_under_another_name(tmp_path):
    # a wrapper that leaves exactly one summary, named differently from the deck
    sim = CommandLineSimulator(template="sh -c 'touch {run_dir}/OTHER.SMSPEC' {deck}")
    res = sim.run(tmp_path / "CASE.DATA", tmp_path / "run")
    assert res.summary_path == tmp_path / "run" / "OTHER.SMSPEC"


# regression: OPM's option parser used to take a deck path holding '=' for an option
@pytest.mark.opm
def test_opm_flow_runs_a_deck_whose_path_contains_equals(tmp_path, punq_dir):
    deck = write_short_deck(tmp_path / "skin=5")
    res = OpmFlow(timeout_s=300).run(deck, tmp_path / "skin=5" / "out=1")
    assert res.summary_path.is_file()
    assert last_time(res.summary_path) == pytest.approx(731.0)


def test_make_simulator():
    assert isinstance(make_simulator(None), OpmFlow)
    assert isinstance(make_simulator("opm", timeout_s=12), OpmFlow)
    assert make_simulator("opm", timeout_s=12).timeout_s == 12
    sim = make_simulator("flow {deck} --output-dir={run_dir}", timeout_s=7)
    assert isinstance(sim, CommandLineSimulator) and sim.timeout_s == 7


# ----------------------------------------------------------------------------- evaluate()
class FakeSimulator:
    """Records calls; raises the given SimulationError or returns a canned SimulationResult."""

    name = "fake"

    def __init__(self, error: SimulationError | None = None, summary: Path | None = None,
                 wall: float = 2.0):
        self.error, self.summary, self.wall, self.calls = error, summary, wall, []

    def run(self, deck: Path, run_dir: Path) -> SimulationResult:
        self.calls.append((deck, run_dir))
        assert deck.is_file() and deck.parent == run_dir  # evaluate prepared the deck first
        if self.error is not None:
            raise self.error
        return SimulationResult(self.summary, run_dir, self.wall, self.name)


@pytest.mark.parametrize("reason", ["parse_error", "timeout", "crash", "no_convergence",
                                    "no_output"])
def test_evaluate_records_fail_and_never_raises(punq_case, tmp_path, reason):
    err = SimulationError(reason, "it went wrong", tmp_path / "run",
                          log_tail="first line\nlast line of the log\n")
    sim = FakeSimulator(error=err)
    ev = evaluate(punq_case, dict(TRUTH_VALUES), tmp_path / "run", sim)
    assert len(sim.calls) == 1
    assert ev.status is Status.FAIL and not ev.selectable
    assert ev.reason == f"{reason}: it went wrong | last line of the log"
    assert math.isnan(ev.E)
    assert ev.penalty == punq_case.physics.failure_penalty  # the truth is physically valid
    assert ev.reward == -punq_case.physics.failure_penalty and math.isfinite(ev.reward)
    assert ev.responses is None
    rec = ev.to_record()
    assert rec["status"] == "FAIL" and rec["reason"] == ev.reason
    json.dumps(rec)  # serialisable


def test_evaluate_physically_impossible_values_are_not_simulated(punq_case, tmp_path):
    sim = FakeSimulator(error=SimulationError("crash", "must not be called"))
    ev = evaluate(punq_case, {**TRUTH_VALUES, "poro_mult": 0.0}, tmp_path / "run", sim)
    assert sim.calls == []
    assert ev.status is Status.FAIL and ev.reason.startswith("not_runnable: physically impossible")
    assert ev.failure is FailureKind.NOT_RUNNABLE
    assert ev.penalty > punq_case.physics.failure_penalty
    assert ev.reward == -ev.penalty


@pytest.mark.opm
def test_evaluate_scores_a_finished_run(punq_case, truth_run, tmp_path):
    sim = FakeSimulator(summary=truth_run.summary_path, wall=3.5)
    ev = evaluate(punq_case, dict(TRUTH_VALUES), tmp_path / "run", sim)
    assert ev.status is Status.COMPLETE and ev.selectable
    expected = score_responses(punq_case, read_responses(truth_run.summary_path,
                                                         sorted(punq_case.info.wells)))
    assert ev.E == pytest.approx(expected["E"], rel=1e-12)
    assert ev.penalty == 0.0 and ev.reward == pytest.approx(-ev.E)
    assert ev.coverage == 1.0
    assert ev.sim_time_s == 3.5 and ev.wall_time_s >= 0.0
    assert set(ev.metrics) == {"macro", "categories", "wells", "excluded"}


@pytest.mark.opm
def test_evaluate_physically_invalid_run_is_penalised_never_best(punq_case, truth_run, tmp_path):
    sim = FakeSimulator(summary=truth_run.summary_path)
    # max PERMX 999 mD x 25 > the 20000 mD cap: simulated and scored, but INVALID
    ev = evaluate(punq_case, {**TRUTH_VALUES, "permx_mult": 25.0}, tmp_path / "run", sim)
    assert ev.status is Status.INVALID and not ev.selectable
    assert ev.penalty > 0 and any("PERMX" in v for v in ev.violations)
    assert ev.reward == pytest.approx(-ev.E - ev.penalty)


@pytest.mark.opm
def test_evaluate_run_that_stopped_early_is_a_fail(punq_case, tmp_path):
    # a real, short OPM run: the same deck with the schedule cut after 1 Jan 1969 (day 731)
    deck = write_short_deck(tmp_path / "short")
    res = OpmFlow(timeout_s=300).run(deck, tmp_path / "short_run")
    assert last_time(res.summary_path) == pytest.approx(731.0)
    sim = FakeSimulator(summary=res.summary_path)
    ev = evaluate(punq_case, dict(TRUTH_VALUES), tmp_path / "run", sim)
    assert ev.status is Status.FAIL
    assert ev.reason.startswith("no_convergence: stopped at day 731")
    assert math.isnan(ev.E) and math.isfinite(ev.reward)


def test_cli_evaluate_failed_run_exits_1_and_records_the_reason(punq_case, punq_case_toml,
                                                                 tmp_path, monkeypatch):
    import hmcore.simulation.simulator
    from hmflow.cli import app

    fake = FakeSimulator(error=SimulationError("timeout", "no result after 1 s", None,
                                               "still stepping"))
    monkeypatch.setattr(hmcore.simulation.simulator, "make_simulator", lambda *a, **k: fake)
    out = tmp_path / "out"
    result = CliRunner().invoke(app, ["evaluate", "--case", str(punq_case_toml), "--set",
                                      "skin=5", "--out", str(out)], env={"COLUMNS": "400"})
    assert result.exit_code == 1, result.output
    assert len(fake.calls) == 1
    doc = json.loads((out / "metrics.json").read_text())
    assert doc["status"] == "FAIL"
    assert doc["reason"] == "timeout: no result after 1 s | still stepping"
    assert doc["misfit"]["E"] is None  # NaN is written as null
    assert not (out / "responses.parquet").exists()


def test_cli_evaluate_refuses_a_non_empty_out_dir(punq_case, punq_case_toml, tmp_path,
                                                  monkeypatch):
    import hmcore.simulation.simulator
    from hmflow.cli import app

    fake = FakeSimulator(error=SimulationError("crash", "must not run"))
    monkeypatch.setattr(hmcore.simulation.simulator, "make_simulator", lambda *a, **k: fake)
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    result = CliRunner().invoke(app, ["evaluate", "--case", str(punq_case_toml), "--out", str(out)])
    assert result.exit_code == 2 and fake.calls == []
    assert (out / "keep.txt").read_text() == "precious"


def test_a_timeout_kills_the_simulator_and_everything_it_started(tmp_path):
    """A wrapper that starts a child of its own (as an MPI launcher or a vendor script does):
    on timeout the whole process group dies, not only the wrapper."""
    import time

    pids = tmp_path / "pids"
    script = tmp_path / "wrapper.sh"
    script.write_text(f"#!/bin/sh\nsleep 60 &\necho $$ $! > {pids}\nwait\n")
    script.chmod(0o755)
    deck = tmp_path / "CASE.DATA"
    deck.write_text("RUNSPEC\n")
    sim = CommandLineSimulator(template=f"{script} {{deck}}", timeout_s=1.0)
    with pytest.raises(SimulationError) as info:
        sim.run(deck, tmp_path / "run")
    assert info.value.reason == "timeout"
    time.sleep(0.5)
    for pid in map(int, pids.read_text().split()):  # gone (or a zombie awaiting its reaper)
        stat = Path(f"/proc/{pid}/stat")
        state = stat.read_text().rsplit(")", 1)[1].split()[0] if stat.exists() else "gone"
        assert state in ("gone", "Z"), (pid, state)


def test_the_peak_memory_of_a_run_is_measured_from_what_the_process_group_used(tmp_path):
    """The group's peak resident memory since exec (not the forked copy of this process a
    child begins as): a wrapper whose child holds 200 MiB for 3 s (the group is looked for
    every second) is measured above that, a process that holds nothing far below."""
    small = run_in_own_group([sys.executable, "-c", "pass"], subprocess.DEVNULL,
                             subprocess.DEVNULL, 60, tmp_path)
    hold = ("import time; b = bytearray(200 * 2**20); b[::4096] = b'x' * len(b[::4096]); "
            "time.sleep(3)")
    child = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {hold!r}])"
    large = run_in_own_group([sys.executable, "-c", child], subprocess.DEVNULL,
                             subprocess.DEVNULL, 60, tmp_path)
    assert small.returncode == 0 and large.returncode == 0
    assert large.peak_rss_bytes > 200 * 2**20 > 4 * small.peak_rss_bytes > 0
    failing = run_in_own_group([sys.executable, "-c", "raise SystemExit(3)"],
                               subprocess.DEVNULL, subprocess.DEVNULL, 60, tmp_path)
    assert failing.returncode == 3
    with pytest.raises(subprocess.TimeoutExpired):
        run_in_own_group(["sleep", "30"], subprocess.DEVNULL, subprocess.DEVNULL, 0.2, tmp_path)
