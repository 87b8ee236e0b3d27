"""The ``[cluster]`` section of a case file (issue 43): bad values refused all at once with
the file and the key, the settings handed to dask-jobqueue, and the walltime and cores checked
against the simulator before any job is submitted (no batch system needed here; the real
Slurm runs in tests/test_slurm.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from flows.runners import task_runner
from hmcore.cases import load_case
from hmcore.errors import CaseError
from hmcore.model.cluster import ClusterKind, ClusterSettings, cluster_problems
from hmcore.model.fingerprint import deck_file_hashes
from storage import ArtifactStore, EvaluationJournal
from storage.peaks import measured_peak


def _case(small_case: Path, root: Path, section: str) -> Path:
    shutil.copytree(small_case.parent, root / "case")
    case = root / "case" / "case.toml"
    case.write_text(case.read_text() + section)
    return case


@pytest.mark.opm
def test_bad_cluster_values_are_refused_all_at_once_with_file_and_key(small_case, tmp_path):
    case = _case(small_case, tmp_path, '\n[cluster]\nmemory = "lots"\nwalltime = "1 hour"\n'
                 'max_jobs = 0\nmax_job = 3\n')
    with pytest.raises(CaseError) as refused:
        load_case(case)
    where = {p.where for p in refused.value.problems}
    assert {f"{case} key 'cluster.{k}'" for k in ("memory", "walltime", "max_jobs",
                                                  "max_job")} <= where, where
    assert any("max_jobs" in p.what + p.fix for p in refused.value.problems
               if p.where.endswith("'cluster.max_job'")), refused.value.problems


@pytest.mark.opm
def test_a_case_s_cluster_section_reaches_dask_jobqueue(small_case, tmp_path):
    case = load_case(_case(small_case, tmp_path, '\n[cluster]\npartition = "short"\ncores = 2\n'
                           'memory = "3GB"\nwalltime = "1-00:00:00"\nmax_jobs = 7\n'
                           'job_directives = ["--constraint=ssd"]\naccount = "geo"\n'))
    runner = task_runner("slurm", 2, cluster=case.cluster)
    assert runner.cluster_class.endswith("SLURMCluster")  # (a class name, not started)
    kwargs = runner.cluster_kwargs
    assert (kwargs["queue"], kwargs["cores"], kwargs["processes"], kwargs["memory"],
            kwargs["walltime"], kwargs["account"]) == ("short", 2, 1, "3GB", "1-00:00:00", "geo")
    assert kwargs["job_extra_directives"] == ["--constraint=ssd"]
    assert (runner.adapt_kwargs["minimum"], runner.adapt_kwargs["maximum"]) == (0, 7)
    assert "project" in ClusterSettings(account="geo").job_kwargs(ClusterKind.PBS)
    assert case.cluster.walltime_s == 86400


def test_walltime_cores_and_memory_are_checked_against_the_simulator():
    settings = ClusterSettings(walltime="00:10:00", cores=1, memory="1GB")
    problems = cluster_problems(settings, timeout_s=900, cores_per_run=2, where="c.toml",
                                peak_bytes=2e9)
    keys = [p.where for p in problems]
    assert keys == ["c.toml key 'cluster.walltime'", "c.toml key 'cluster.cores'",
                    "c.toml key 'cluster.memory'"], keys
    assert "00:17:00" in problems[0].fix  # 900 s + the worker's start
    assert cluster_problems(ClusterSettings(walltime="00:17:00"), 900, 1, "c.toml") == []


def _stored_runs(store: ArtifactStore, campaign: str, deck_files: dict, peaks: list,
                 journal: str | None = None) -> None:
    """A campaign of the deck whose files hash to ``deck_files``, with one journal record per
    peak (None: a run that was not measured)."""
    store.put(campaign, "case", {"deck_files": deck_files},
              lambda d: (d / "case.json").write_text("{}"), "test")
    for i, peak in enumerate(peaks):
        EvaluationJournal(store, campaign, journal).record(
            i, {"status": "COMPLETE", "peak_rss_bytes": peak})


def test_the_highest_measured_peak_of_the_same_deck_is_found_in_every_journal(tmp_path):
    store = ArtifactStore(tmp_path / "store")
    deck = {"DECK.DATA": "a" * 64, "GRID.INC": "b" * 64}
    assert measured_peak(store, deck) is None  # no store yet
    _stored_runs(store, "calib", deck, [1.0e8, None, 2.5e8])
    _stored_runs(store, "diag", deck, [3.0e8], journal="diagnosis")
    _stored_runs(store, "other-deck", {**deck, "GRID.INC": "c" * 64}, [9.0e9])
    peak = measured_peak(store, deck)
    assert (peak.bytes, peak.campaign, peak.index, peak.runs) == (3.0e8, "diag", 0, 3)
    assert measured_peak(store, {"DECK.DATA": "a" * 64}) is None  # another set of files


@pytest.mark.opm
def test_a_job_memory_below_the_measured_peak_is_refused_before_any_job(small_case, tmp_path):
    from typer.testing import CliRunner

    from hmflow.cli import app

    case_file = _case(small_case, tmp_path, '\n[cluster]\nmemory = "200MB"\n')
    store = ArtifactStore(tmp_path / "store")
    _stored_runs(store, "earlier", deck_file_hashes(load_case(case_file)), [1.1e8, 1.9e8])
    args = ["run", "--case", str(case_file), "--cluster", "slurm", "--budget", "2",
            "--campaign", "new", "--storage", str(store.root)]
    out = CliRunner().invoke(app, args, env={"COLUMNS": "300", "NO_COLOR": "1"})
    text = " ".join(out.output.split())
    assert out.exit_code == 2, out.output
    assert "cluster.memory" in text and "190 MB" in text and "campaign earlier" in text, text
    assert "memory >= 0.24GB" in text, text  # 1.25 x 190 MB
    assert not (store.root / "new" / "evaluations").exists()  # nothing simulated
    assert "Traceback" not in out.output
