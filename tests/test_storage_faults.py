"""Storage faults as one line (issue 43): a store on a small tmpfs that fills in the middle of
a real campaign (real OPM Flow on the small synthetic case, real Prefect, the session's server)
ends with one line naming the path and the fix, a non-zero exit and no traceback; every stored
version is intact; after space is freed the same command finishes with no call simulated
twice. A read-only store and a removed store are refused in one line too. Mounting a tmpfs
needs root: skipped otherwise."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import cli_env

from storage import ArtifactStore
from storage.space import is_fault, require_store
from tasks.results import report

BUDGET = 4
FIX = "and run the same command again: it resumes"


def _hmflow(*args: str, cwd: Path, api: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "hmflow.cli", *args], cwd=cwd,
                            env=cli_env(api, COLUMNS="200"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


@pytest.fixture
def small_disk(tmp_path):
    """A 48 MB tmpfs at ``tmp_path/disk`` (unmounted afterwards)."""
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    mnt = tmp_path / "disk"
    mnt.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=48m", "tmpfs", str(mnt)],
                             capture_output=True, text=True, timeout=30, check=False)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30, check=False)


def _fill(path: Path) -> int:
    """Write ``path`` until the file system is full; the bytes written."""
    written = 0
    with open(path, "wb", buffering=0) as f:
        for chunk in (1 << 20, 1 << 12):
            block = b"\0" * chunk
            while True:
                try:
                    written += f.write(block)
                except OSError:
                    break
    return written


def _records(evaluations: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(evaluations.glob("*.json"))}


def _problem_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("x ")]


@pytest.mark.opm
def test_a_disk_that_fills_mid_campaign_ends_in_one_line_and_the_same_command_finishes(
        small_disk, small_case, prefect_api, tmp_path):
    store = small_disk / "store"
    args = ("run", "--case", str(small_case), "--agent", "random", "--budget", str(BUDGET),
            "--workers", "1", "--seed", "9", "--campaign", "full", "--storage", str(store))
    evaluations = store / "full" / "evaluations"
    first = _hmflow(*args, cwd=tmp_path, api=prefect_api)
    deadline = time.monotonic() + 600
    while len(_records(evaluations)) < 2 and first.poll() is None \
            and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(_records(evaluations)) >= 2, first.communicate()
    ballast = small_disk / "ballast"
    assert _fill(ballast) > 0
    out, err = first.communicate(timeout=600)
    assert first.returncode != 0, out + err
    assert "Traceback" not in out + err, out + err
    lines = _problem_lines(err)
    assert len(lines) == 1, err
    assert "storage fault: no space left at " + str(store) in lines[0], lines[0]
    assert "free space " + FIX in lines[0], lines[0]
    kept = _records(evaluations)
    assert 2 <= len(kept) < BUDGET, sorted(kept)
    # no version that looks complete is half-written (each one verifies against its manifest)
    archive = ArtifactStore(store)
    for campaign in archive.campaigns():
        for step in archive.steps(campaign):
            for version in archive.versions(campaign, step):
                assert version.verify() == [], (campaign, step, version.version)

    ballast.unlink()
    again = _hmflow(*args, cwd=tmp_path, api=prefect_api)
    out2, err2 = again.communicate(timeout=600)
    assert again.returncode == 0, out2 + err2
    assert f"resuming campaign full: {len(kept)} calls already journaled" in out2
    finished = _records(evaluations)
    assert sorted(finished) == [f"{i:06d}.json" for i in range(BUDGET)]
    # the calls journaled before the disk filled were not simulated again: their records
    # are the same bytes, and no second run directory was made for any of them
    assert {name: finished[name] for name in kept} == kept
    runs = store / "full" / "runs"
    for name in kept:
        index = name.removesuffix(".json")
        assert json.loads(kept[name])["run_dir"] == str(runs / index)
        assert not (runs / f"{index}.2").exists()


@pytest.mark.opm
def test_a_read_only_store_is_refused_in_one_line(small_disk, small_case, prefect_api,
                                                  tmp_path):
    store = small_disk / "store"
    store.mkdir()
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True, timeout=30)
    run = _hmflow("run", "--case", str(small_case), "--agent", "random", "--budget", "1",
                  "--campaign", "ro", "--storage", str(store), cwd=tmp_path, api=prefect_api)
    out, err = run.communicate(timeout=300)
    assert run.returncode != 0, out + err
    assert "Traceback" not in out + err, out + err
    lines = _problem_lines(err)
    assert len(lines) == 1 and "read-only file system at " + str(store) in lines[0], err
    assert "make the store writable" in lines[0] and FIX in lines[0]


def test_a_store_removed_while_running_is_a_fault_naming_it(tmp_path):
    store = tmp_path / "store"
    store.mkdir()
    assert require_store(store) == store
    store.rmdir()
    with pytest.raises(FileNotFoundError) as gone:
        require_store(store)
    assert gone.value.filename == str(store)


@pytest.mark.opm
def test_a_report_on_a_store_removed_under_it_is_a_storage_fault(tmp_path):
    """The report step of a flow whose store went away (after the calls, before the report:
    the window the test below may hit) raises the store's fault, which the command says in
    one line, not a missing-results error with a traceback."""
    store = tmp_path / "store"
    ArtifactStore(store).bind_settings("gone", {"agent": "random"})
    shutil.rmtree(store)
    with pytest.raises(FileNotFoundError) as caught:
        report.fn(str(store), "gone", publish_prefect_artifacts=False)
    assert is_fault(caught.value, store) and str(store / "gone") == caught.value.filename


def test_a_store_removed_mid_campaign_ends_in_one_line(small_case, prefect_api, tmp_path):
    store = tmp_path / "store"
    run = _hmflow("run", "--case", str(small_case), "--agent", "random", "--budget", "4",
                  "--workers", "1", "--seed", "8", "--campaign", "gone", "--storage", str(store),
                  cwd=tmp_path, api=prefect_api)
    evaluations = store / "gone" / "evaluations"
    deadline = time.monotonic() + 600
    while not _records(evaluations) and run.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert _records(evaluations), run.communicate()
    shutil.rmtree(store)
    out, err = run.communicate(timeout=600)
    assert run.returncode != 0, out + err
    assert "Traceback" not in out + err, out + err
    lines = _problem_lines(err)
    assert len(lines) == 1 and "storage fault: " in lines[0], err
    assert str(store) in lines[0] and "restore or recreate the store's folder" in lines[0]
    assert not store.exists()  # no new, empty store started under the same path
