"""What the terminal shows: Prefect's own log lines only with --verbose, no telemetry error, calls
numbered from 1, one summary table at the end of `hmflow run`, and progress bars for `run`,
`bench` and `diagnose` that never break the command (real OPM + real Prefect for `run`; the
bench and diagnose bars with stand-in flows that write the files the bars poll)."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from rich.console import Console

import hmflow.console as term

LOG_LINE = re.compile(r"\d\d:\d\d:\d\d\.\d{3} \| [A-Z]+\s+\| ")  # a line of Prefect's console log
INFO_LINE = re.compile(r"\| INFO\s+\|")  # Prefect's console format: "12:00:00.000 | INFO    | ..."
TELEMETRY = ("Failed to send telemetry", "sens-o-matic", "anonymous usage data")


def hmflow(*args: str, cwd: Path, env: dict | None = None, timeout: int = 600,
           columns: int = 220) -> subprocess.CompletedProcess:
    """`hmflow ARGS` writing to pipes, ``columns`` wide."""
    env = {**(os.environ if env is None else env), "COLUMNS": str(columns)}
    return subprocess.run([sys.executable, "-m", "hmflow.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout, check=False)


def clean_env() -> dict:
    """This environment without the variables hmflow sets (a user who set none of them)."""
    return {k: v for k, v in os.environ.items()
            if k not in ("PREFECT_SERVER_ANALYTICS_ENABLED", "DO_NOT_TRACK", "PREFECT_LOGGING_LEVEL",
                         term.CONSOLE_LEVEL_VAR)}


# ------------------------------------------------------------------ real OPM, real Prefect
@pytest.mark.opm
def test_run_is_quiet_numbers_calls_from_1_and_ends_on_one_summary_table(tmp_path, small_case,
                                                                        prefect_api):
    """What the terminal shows of `hmflow run` with its own temporary Prefect server (the
    small synthetic case, conftest.small_case: the printing is tested, not the case), at 80
    columns in a pipe; `hmflow report` of it, and the run resumed with --verbose, on a
    configured server (the session's, conftest.prefect_api)."""
    store = tmp_path / "a-store-with-a-long-name-so-that-its-report-path-is-longer-than-80-columns"
    common = ("run", "--case", str(small_case), "--agent", "random", "--seed", "3",
              "--workers", "1", "--storage", str(store))
    quiet = hmflow(*common, "--budget", "2", cwd=tmp_path, env=clean_env(), columns=80)
    text = quiet.stdout + quiet.stderr
    assert quiet.returncode == 0, text
    # the campaign's name when the run starts and ends, paths and commands never broken
    lines = quiet.stdout.splitlines()
    start = lines.index(f"storage: {store}")
    assert " ".join(" ".join(lines[:start]).split()) == ("campaign synthetic-small-random-seed3: case "
                                       "synthetic-small, agent random, budget 2, workers 1, seed 3")
    assert lines[-2:] == ["campaign synthetic-small-random-seed3 done; to print its report again:",
                          f"  hmflow report --campaign synthetic-small-random-seed3 --storage {store}"]
    assert_80_columns(quiet.stdout, store)
    assert not INFO_LINE.search(text), text           # Prefect's INFO lines stay out
    assert "Traceback" not in text and not any(t in text for t in TELEMETRY), text
    assert "2/2" in quiet.stdout                      # the progress bar reached the budget
    assert "calls: 1 valid, 1 penalised" in quiet.stdout   # no raw {'COMPLETE': 1, ...} dict
    assert "{'" not in quiet.stdout
    # the summary table comes last: best E with its call numbered from 1, the paper's three
    # headline numbers, failed / penalised calls and where the report is
    summary = quiet.stdout[quiet.stdout.rindex("Summary"):]
    doc = json.loads(next(store.glob("*/report/v0001/report.json")).read_text())
    best = doc["best"]
    assert re.search(rf"E of the best call\s+│ {best['E']:.6g} \(call {best['index'] + 1} of 2\)",
                     summary)
    assert not re.search(r"call 0\b", text)
    assert f"macro NMSE         │ {best['macro']['nmse']:.4f}" in summary
    assert f"macro R²           │ {best['macro']['r2']:.4f}" in summary
    assert f"C_match            │ {best['macro']['cmatch']:.2f} %" in summary
    assert "failed / penalised │ 0 failed, 1 penalised (of 2 calls)" in summary
    where = re.search(r"^report: (.+)$", summary, re.MULTILINE).group(1)     # a line of its own
    assert Path(where).is_file() and Path(where).name in ("report.html", "report.md")

    # the same report rebuilt from the store, printed at 80 columns in a pipe
    rep = hmflow("report", "--storage", str(store), "--campaign", "synthetic-small-random-seed3",
                 cwd=tmp_path, env={**clean_env(), "PREFECT_API_URL": prefect_api}, columns=80)
    assert rep.returncode == 0, rep.stdout + rep.stderr
    assert f"best call {best['index'] + 1} (calls numbered from 1)" in rep.stdout
    assert_80_columns(rep.stdout, store)
    where = re.findall(r"^report: (.+)$", rep.stdout, re.MULTILINE)[-1]
    assert Path(where).is_file() and Path(where).is_relative_to(store)

    # --verbose: the same campaign resumed to 3 calls, Prefect's INFO lines shown - printed by
    # the bar's own console, so that no log line is written into the bar
    loud = hmflow(*common, "--budget", "3", "--verbose", cwd=tmp_path,
                  env={**clean_env(), "PREFECT_API_URL": prefect_api})
    text = loud.stdout + loud.stderr
    assert loud.returncode == 0, text
    assert INFO_LINE.search(text) and "Beginning flow run" in text, text
    assert "Traceback" not in text and not any(t in text for t in TELEMETRY), text
    assert "resuming campaign synthetic-small-random-seed3: 2 calls already journaled" in loud.stdout
    bar = [line for line in loud.stdout.splitlines() if line.startswith("calls ")]
    assert bar and all(not INFO_LINE.search(line) for line in bar), bar
    assert "3/3" in bar[-1] and re.search(r"\(call [1-3] of 3\)", loud.stdout)
    assert not re.search(r"call 0\b", text)


def assert_80_columns(out: str, store: Path) -> None:
    """Nothing cut (no ellipsis) and no line over 80 columns but those that hold a path under
    ``store``, which are never broken: a path is on a line of its own and whole. (Prefect's own
    log lines, a warning of a library, are not hmflow's printing.)"""
    assert "…" not in out, out
    lines = [line for line in out.splitlines() if not LOG_LINE.match(line)]
    long = [line for line in lines if len(line) > 80]
    assert long and all(str(store) in line for line in long), long
    assert all(line.endswith(str(store)) or re.search(rf"{re.escape(str(store))}/\S+$", line)
               for line in lines if str(store) in line), out
    # a path broken anywhere leaves the start of the store's name without the whole path
    assert out.count(store.name[:12]) == out.count(str(store)), out


def test_prefect_reads_the_quiet_defaults_and_a_users_own_values_win(tmp_path):
    """In a fresh process, as `hmflow` starts: Prefect's console handler is at WARNING and
    server analytics are off; values the user set are left alone."""
    probe = ("import json, logging, os\nfrom typer.testing import CliRunner\n"
             "from hmflow.cli import app\nCliRunner().invoke(app, ['check', '--help'])\n"
             "from prefect import flow\n"
             "from prefect.settings import get_current_settings\n"
             "h = [h for h in logging.getLogger().handlers\n"
             "     if type(h).__name__ == 'PrefectConsoleHandler']\n"
             "print(json.dumps({'level': h[0].level, 'dnt': os.environ.get('DO_NOT_TRACK'),\n"
             "                  'analytics': get_current_settings().server.analytics_enabled}))\n")

    def run(env):
        p = subprocess.run([sys.executable, "-c", probe], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=120, check=False)
        assert p.returncode == 0, p.stdout + p.stderr
        return json.loads(p.stdout.strip().splitlines()[-1])

    assert run(clean_env()) == {"level": 30, "dnt": "1", "analytics": False}
    own = run({**clean_env(), "PREFECT_LOGGING_LEVEL": "DEBUG", "DO_NOT_TRACK": "0",
               "PREFECT_SERVER_ANALYTICS_ENABLED": "true"})
    assert own == {"level": 0, "dnt": "0", "analytics": True}


# ------------------------------------------------------------------------- in process, fast
def test_verbose_undoes_only_hmflows_own_quiet_default(monkeypatch, restore_env):
    levels = []
    monkeypatch.setattr(term, "_set_console_handler_level", levels.append)
    for k in ("PREFECT_LOGGING_LEVEL", term.CONSOLE_LEVEL_VAR, "DO_NOT_TRACK",
              "PREFECT_SERVER_ANALYTICS_ENABLED"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setattr(term, "_quieted", False)
    term.prefect_environment()
    assert os.environ[term.CONSOLE_LEVEL_VAR] == "WARNING" and levels == [30]
    assert os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] == "false"
    term.prefect_environment(verbose=True)
    assert term.CONSOLE_LEVEL_VAR not in os.environ and levels == [30, 0]
    # a level the user set is theirs: neither quiet nor verbose changes it
    monkeypatch.setenv("PREFECT_LOGGING_LEVEL", "ERROR")
    term.prefect_environment()
    term.prefect_environment(verbose=True)
    assert term.CONSOLE_LEVEL_VAR not in os.environ and levels == [30, 0]
    monkeypatch.delenv("PREFECT_LOGGING_LEVEL")
    monkeypatch.setenv(term.CONSOLE_LEVEL_VAR, "ERROR")
    term.prefect_environment(verbose=True)
    assert os.environ[term.CONSOLE_LEVEL_VAR] == "ERROR"


def _text(renderable) -> str:
    c = Console(width=120, record=True, file=io.StringIO())
    c.print(renderable)
    return c.export_text()


def test_summary_table_numbers_calls_from_1_and_reads_without_a_best_case():
    doc = {"campaign": "c", "calls": 5, "status_counts": {"COMPLETE": 3, "INVALID": 1, "FAIL": 1},
           "best": {"index": 0, "E": 0.0123456789, "macro": {"nmse": 0.02853, "r2": 0.9712,
                                                             "cmatch": 97.226}}}
    text = _text(term.summary_table(doc, "/x/report.html"))
    assert "0.0123457 (call 1 of 5)" in text and "call 0" not in text
    assert "0.0285" in text and "0.9712" in text and "97.23 %" in text
    assert "1 failed, 1 penalised (of 5 calls)" in text and "/x/report.html" in text
    none = _text(term.summary_table({"campaign": "c", "calls": 2, "best": None,
                                     "status_counts": {"FAIL": 2}}, "r.md"))
    assert "none: no valid call of 2" in none and "macro" not in none and "2 failed" in none
    diag = _text(term.summary_table({"campaign": "d", "calls": 0, "best": None}, "r.md"))
    assert "no calibration calls" in diag and "failed" not in diag
    assert term.status_text({"COMPLETE": 3, "INVALID": 0, "FAIL": 2}) == "3 valid, 2 failed"


def test_polls_survive_missing_files_and_count_what_appears(tmp_path):
    from storage import ArtifactStore, EvaluationJournal

    campaigns = {"b-random-s0": ("random", 0), "b-lm-s0": ("lm", 0), "b-random-s1": ("random", 1)}
    poll = term.bench_poll(tmp_path / "nowhere", campaigns, 2)
    assert poll() == {"completed": 0, "current": "reference runs"}
    store = ArtifactStore(tmp_path)
    for i in range(3):  # more calls than the budget count as the budget
        EvaluationJournal(store, "b-random-s0").record(i, {"status": "COMPLETE", "E": 1.0 + i})
    EvaluationJournal(store, "b-lm-s0").record(0, {"status": "FAIL", "E": None})
    assert term.bench_poll(tmp_path, campaigns, 2)() == {"completed": 3, "current": "lm seed 0"}
    # calls stored under other settings are not counted: a resume the flow refuses never
    # shows a full bar first
    from flows.bench import same_settings
    from hmcore.calibration.methods import method_version
    from hmcore.scoring.evaluation import SCORING_VERSION

    (tmp_path / "b-random-s0" / "campaign.json").write_text(json.dumps(
        {"agent": "random", "seed": 0, "workers": 2, "scoring_version": SCORING_VERSION,
         "method_version": method_version("random")}))
    assert same_settings(tmp_path, "b-random-s0", "random", 0, 2) is True
    assert same_settings(tmp_path, "b-lm-s0", "lm", 0, 2) is None
    assert term.bench_poll(tmp_path, campaigns, 2, 2)()["completed"] == 3
    assert term.bench_poll(tmp_path, campaigns, 2, 1)() == {"completed": 1,
                                                           "current": "random seed 0"}
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "campaign.json").write_text(json.dumps({"budget": 2, "workers": 2}))
    assert term.bench_poll(tmp_path, campaigns, 2, 2, "b")()["completed"] == 3
    assert term.bench_poll(tmp_path, campaigns, 3, 2, "b")() == {
        "completed": 0, "current": "b was stored with another budget or worker count"}
    (tmp_path / "b" / "campaign.json").write_text(json.dumps({"case_artifact": {}}))
    assert term.bench_poll(tmp_path, campaigns, 3, 2, "b")()["completed"] == 4  # older store
    assert term.campaign_poll(tmp_path, "b-random-s0", 2)() == {"completed": 2, "best": "1"}
    assert term.campaign_poll(tmp_path, "absent", 2)() == {}

    runs = tmp_path / "d" / "diagnosis-runs"
    runs.mkdir(parents=True)
    (runs / "calibration-00000").mkdir()  # an earlier diagnosis's: not counted
    diag = term.diagnosis_poll(tmp_path, "d")
    assert term.diagnosis_poll(tmp_path, "absent")() == {}
    assert diag() == {"completed": 0, "step": "-"}
    for name in ("calibration-00000.2", "ranking-00001", "restart-grid-00002"):
        (runs / name).mkdir()
    assert diag() == {"completed": 3, "step": "restart-grid"}


def test_a_failing_poll_never_fails_the_command_and_the_bar_ends_on_the_last_count():
    console = Console(width=100, record=True, file=io.StringIO())
    calls = []

    def poll():
        calls.append(1)
        if len(calls) < 3:
            raise ValueError("a record being replaced")
        return {"completed": 4, "best": "0.5"}

    from hmflow.cli.flowrun import progress_columns as _columns

    with term.Watch(console, poll, _columns("run"), total=4, initial={"best": "-"},
                    interval=0.01):
        time.sleep(0.1)
    assert len(calls) >= 3  # polled again after the failures
    text = console.export_text()
    assert "4/4" in text and "lowest E 0.5" in text


def test_prefect_log_lines_go_through_the_bars_console_while_it_runs():
    import logging

    from prefect.logging.handlers import PrefectConsoleHandler

    handler = PrefectConsoleHandler(stream=io.StringIO())
    own = handler.console
    logger = logging.getLogger("hmflow-test-terminal")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        console = Console(width=100, record=True, file=io.StringIO())
        with term.Watch(console, lambda: {"completed": 1}, ["{task.completed}/{task.total}"],
                        total=1, interval=0.01):
            logger.warning("a [bold]warning[/] while the bar runs")
        assert handler.console is own  # restored
        text = console.export_text()
        assert "a [bold]warning[/] while the bar runs" in text  # as plain text, not markup
    finally:
        logger.removeHandler(handler)


@pytest.mark.opm  # the built-in case is written (one OPM run) on first use
def test_bench_and_diagnose_show_a_progress_bar(tmp_path, monkeypatch, restore_env, prefect_api):
    """`hmflow bench` and `hmflow diagnose` with stand-in flows that write what the real ones
    write (journal records; diagnosis run directories) while the command's bar polls them (the
    session's Prefect server as the configured API: no temporary server per command)."""
    monkeypatch.setenv("PREFECT_API_URL", prefect_api)
    from typer.testing import CliRunner

    import flows.bench
    import flows.diagnose
    from hmflow.cli import app
    from storage import ArtifactStore, EvaluationJournal

    class Stand:
        def __init__(self, body):
            self.body = body

        def with_options(self, **_):
            return self

        def __call__(self, **kw):
            return self.body(**kw)

    def bench(storage, methods, seeds, budget, name, **_):
        store = ArtifactStore(storage)
        for s in seeds:
            for m in methods:
                for i in range(budget):
                    EvaluationJournal(store, f"{name}-{m}-s{s}").record(i, {"status": "COMPLETE"})
                    time.sleep(0.05)
        summary = Path(storage) / "summary.md"
        summary.write_text("| method |\n")
        return {"summary_path": str(summary), "plot_path": str(Path(storage) / "p.png")}

    monkeypatch.setattr(flows.bench, "bench_flow", Stand(bench))
    storage = tmp_path / "store"
    out = CliRunner().invoke(app, ["bench", "--methods", "random,sobol", "--seeds", "2",
                                   "--budget", "2", "--workers", "1", "--storage", str(storage),
                                   "--name", "b"], env={"COLUMNS": "150"})
    assert out.exit_code == 0, out.output
    bar = [line for line in out.output.splitlines() if line.startswith("calls ")]
    assert bar and "8/8" in bar[-1] and "every method and seed done" in bar[-1], out.output

    def diagnose(storage, campaign, **_):
        runs = Path(storage) / campaign / "diagnosis-runs"
        for n, step in enumerate(["calibration"] * 3 + ["ranking"] * 2):
            (runs / f"{step}-{n:05d}").mkdir(parents=True)
            time.sleep(0.05)
        return {"done": True}

    shown = []
    monkeypatch.setattr(flows.diagnose, "diagnose_flow", Stand(diagnose))
    monkeypatch.setattr(flows.diagnose, "print_diagnosis", lambda r, c: shown.append(r))
    out = CliRunner().invoke(app, ["diagnose", "--storage", str(storage), "--campaign", "d",
                                   "--workers", "1"], env={"COLUMNS": "150"})
    assert out.exit_code == 0, out.output
    assert shown == [{"done": True}]
    assert re.search(r"simulations 5 .*step ranking", out.output), out.output
    out = CliRunner().invoke(app, ["diagnose", "--storage", str(storage), "--campaign", "d2",
                                   "--budget", "45", "--workers", "1"], env={"COLUMNS": "150"})
    assert out.exit_code == 0, out.output
    assert re.search(r"simulations \(budget 45\) .*5/45 .*step ranking", out.output), out.output
