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
