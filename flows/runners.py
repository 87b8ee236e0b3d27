"""Where a flow's simulator calls run, chosen by a flow parameter (so the CLI and a deployment
choose alike): ``threads`` (a thread pool in the flow's process, each simulation its own
subprocess) or ``dask`` (a Dask cluster: the one at ``dask_address`` or ``DASK_ADDRESS``,
whose workers may be on other machines, else a local one with ``workers`` processes), or a
batch system's queue: ``slurm``, ``pbs``, ``lsf`` (dask-jobqueue: the same Dask runner, whose
workers are batch jobs, one single-threaded worker per job, submitted as the work needs them
between 0 and the case's ``[cluster] max_jobs``; :mod:`hmcore.model.cluster`).

The flow enters the runner itself and submits ``simulate`` tasks to it, so the choice is made
at run time, not when the flow is decorated or deployed. Results and run directories go to
the shared store (an absolute path every worker sees); nothing lives only in worker memory.
A Dask worker that dies mid-call (a cancelled or timed-out batch job too) has its task rerun
on another worker by the Dask scheduler (``distributed.scheduler.allowed-failures``, 3 by
default); the call's record is write-once
in the journal and its run directory is fresh (``tasks.simulate.fresh_dir``), so a rerun
neither loses nor duplicates an evaluation.
"""

from __future__ import annotations

import os
from typing import Literal

from hmcore.model.cluster import CLUSTER_KINDS, ClusterKind, ClusterSettings

IDLE_JOB_S = 60
"""How long (s) a batch job's worker may idle before the adaptive cluster releases it: longer
than the method's pause between two batches of calls, or each batch waits for new jobs to
start (with Dask's 3 s, 7 jobs were submitted for 8 calls and one ran them all)."""
Runner = Literal["threads", "dask", "slurm", "pbs", "lsf"]
RUNNERS = ("threads", "dask", *CLUSTER_KINDS)


def task_runner(kind: str, workers: int, dask_address: str | None = None,
                cluster: ClusterSettings | None = None):
    """A Prefect task runner (not started: enter it with ``with``); ``cluster``: the case's
    ``[cluster]`` section, for a batch system's kind."""
    if kind == "threads":
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=workers)
    if kind == "dask":
        from prefect_dask import DaskTaskRunner

        address = dask_address or os.environ.get("DASK_ADDRESS")
        if address:
            return DaskTaskRunner(address=address)
        return DaskTaskRunner(cluster_kwargs={"n_workers": workers, "threads_per_worker": 1,
                                              "processes": True,
                                              "dashboard_address": "127.0.0.1:0"})
    if kind in CLUSTER_KINDS:
        from prefect_dask import DaskTaskRunner

        batch = ClusterKind(kind)
        settings = cluster or ClusterSettings()
        return DaskTaskRunner(cluster_class=batch.cluster_class,
                              cluster_kwargs={**settings.job_kwargs(batch),
                                              "scheduler_options": {"dashboard_address": ":0"},
                                              "job_name": "hmflow"},
                              adapt_kwargs={"minimum": 0, "maximum": settings.max_jobs,
                                            "interval": "1s", "wait_count": IDLE_JOB_S})
    raise ValueError(f"task_runner must be one of {list(RUNNERS)}, got {kind!r}")
