"""Fault injection: a command-line simulator built to fail in every way a real one does (crash,
killed by a signal, hang past the timeout, exit 0 without a summary, a garbage, empty or
SMSPEC-only summary, non-finite values). A real campaign (Prefect flow, store, report) runs
to the end, each call recorded FAIL with its kind decided from facts, and no process it
started is left alive."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

# mode by call number (the run directory's name), so one campaign meets every fault
FAULTY = r'''
import os, re, shutil, signal, sys, time
deck, run_dir = sys.argv[1], sys.argv[2]
index = int(re.match(r"(\d+)", os.path.basename(run_dir.rstrip("/"))).group(1))
modes = ["crash", "killed", "hang", "no_output", "garbage", "empty", "smspec_only", "nan"]
mode = modes[index % len(modes)]
case = os.path.splitext(os.path.basename(deck))[0].upper()
def out(ext):
    return os.path.join(run_dir, case + ext)
if mode == "crash":
    sys.exit(1)
if mode == "killed":
    os.kill(os.getpid(), signal.SIGKILL)
if mode == "hang":
    child = os.fork()          # a child of its own, as an MPI launcher has
    time.sleep(120)
if mode == "no_output":
    sys.exit(0)
if mode == "garbage":
    open(out(".SMSPEC"), "wb").write(os.urandom(4000))
    open(out(".UNSMRY"), "wb").write(os.urandom(4000))
if mode == "empty":
    open(out(".SMSPEC"), "wb").close()
    open(out(".UNSMRY"), "wb").close()
if mode in ("smspec_only", "nan"):
    shutil.copy(os.environ["HMFLOW_TEST_SMSPEC"], out(".SMSPEC"))
    if mode == "nan":
        shutil.copy(os.environ["HMFLOW_TEST_UNSMRY_NAN"], out(".UNSMRY"))
'''
EXPECTED = ["crash", "killed", "timeout", "no_output", "unreadable_output", "unreadable_output",
            "unreadable_output", "invalid_values"]


def _nan_summary(truth_dir: Path, dest: Path) -> tuple[Path, Path]:
    """A real summary of the synthetic deck with one value replaced by NaN (float32 bits)."""
    import numpy as np
    from opm.io.ecl import EclFile, ESmry

    smspec = next(truth_dir.glob("*.SMSPEC"))
    unsmry = smspec.with_suffix(".UNSMRY")
    data = bytearray(unsmry.read_bytes())
    smry = ESmry(str(smspec))
    key = next(k for k in smry.keys() if k.startswith("WBHP:"))
    value = np.float32(smry[key][-1]).tobytes()[::-1]  # big-endian, as Eclipse files are
    at = data.rfind(value)
    assert at > 0
    data[at:at + 4] = np.float32(np.nan).tobytes()[::-1]
    shutil.copy(smspec, dest / "NAN.SMSPEC")
    (dest / "NAN.UNSMRY").write_bytes(bytes(data))
    del EclFile
    return dest / "NAN.SMSPEC", dest / "NAN.UNSMRY"


@pytest.mark.opm
def test_a_campaign_survives_every_fault_and_records_its_kind(tmp_path, monkeypatch,
                                                             small_case):
    src = small_case.parent  # the small synthetic case (conftest.small_case)
    case_dir = tmp_path / "case"
    case_dir.mkdir()
    for name in ("SYNTH.DATA", "observed.csv"):
        shutil.copy(src / name, case_dir / name)
    (tmp_path / "faulty.py").write_text(FAULTY)
    toml = (src / "case.toml").read_text() + (
        f'\n[simulator]\nbackend = "{sys.executable} {tmp_path / "faulty.py"} {{deck}} '
        f'{{run_dir}}"\ntimeout_s = 3\n')
    (case_dir / "case.toml").write_text(toml)
    # one real run of the synthetic deck, for the SMSPEC-only and NaN summaries
    real = tmp_path / "real"
    run = subprocess.run([sys.executable, "-m", "hmflow.cli", "evaluate", "--case", str(small_case),
                          "--out", str(real)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=600)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    run_dir = next(p.parent for p in real.rglob("*.SMSPEC"))
    smspec, unsmry = _nan_summary(run_dir, tmp_path)
    env = {**__import__("os").environ, "HMFLOW_TEST_SMSPEC": str(smspec),
           "HMFLOW_TEST_UNSMRY_NAN": str(unsmry)}
    proc = subprocess.Popen([sys.executable, "-m", "hmflow.cli", "run", "--case",
                             str(case_dir / "case.toml"), "--agent", "random", "--budget",
                             str(len(EXPECTED)), "--workers", "2", "--campaign", "faults",
                             "--storage", str(tmp_path / "store")], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    out, _ = proc.communicate(timeout=900)
    assert proc.returncode == 0 and "Traceback" not in out, out[-4000:]
    rows = [json.loads(p.read_text()) for p in
            sorted((tmp_path / "store" / "faults" / "evaluations").glob("*.json"))]
    assert [r["index"] for r in rows] == list(range(len(EXPECTED)))
    assert [r["status"] for r in rows] == ["FAIL"] * len(EXPECTED)
    assert [r["failure"] for r in rows] == EXPECTED, [(r["failure"], r["reason"]) for r in rows]
    assert all(r["reason"].startswith(r["failure"]) for r in rows)
    killed = rows[EXPECTED.index("killed")]
    assert killed["attempts"] == 3  # killed from outside: retried; nothing else is
    assert all(r["attempts"] == 1 for r in rows if r["failure"] != "killed")
    # nothing the campaign started is alive: no simulator, no hung child, no server
    ps = subprocess.run(["ps", "-eo", "pid=,args="], capture_output=True, text=True).stdout
    assert str(tmp_path / "faulty.py") not in ps, ps
    report = next((tmp_path / "store" / "faults" / "report").glob("v*/report.md")).read_text()
    # the report names every failure in words, with its count (issue 45's one vocabulary)
    line = next(x for x in report.splitlines() if x.startswith("Failed calls by reason: "))
    for kind in set(EXPECTED):
        assert f"{kind.replace('_', ' ')} {EXPECTED.count(kind)}" in line, line
