"""The ``[cluster]`` section of a case file: the batch jobs whose Dask workers run a flow's
simulator calls when it runs with ``--cluster slurm|pbs|lsf`` (:mod:`flows.runners` hands
these settings to dask-jobqueue).

Every job is one Dask worker of one thread; each simulator call runs inside a job. The
cluster grows and shrinks with the work (adaptive, between 0 and ``max_jobs`` jobs).

Checked before anything is submitted (:func:`cluster_problems`): a job's walltime must hold a
whole call (the simulator's ``timeout_s``, plus the worker's start), its cores a run's
``threads x processes``, and its memory a run's measured peak when one is known.
"""

from __future__ import annotations

import re
from enum import Enum

from pydantic import AliasChoices, BaseModel, ConfigDict, Field

from hmcore.errors import Problem


class ClusterKind(str, Enum):
    """A batch system dask-jobqueue submits to."""

    SLURM = "slurm"
    PBS = "pbs"
    LSF = "lsf"

    @property
    def cluster_class(self) -> str:
        """dask-jobqueue's cluster class for this batch system."""
        return {"slurm": "dask_jobqueue.SLURMCluster", "pbs": "dask_jobqueue.PBSCluster",
                "lsf": "dask_jobqueue.LSFCluster"}[self.value]


CLUSTER_KINDS = tuple(k.value for k in ClusterKind)
WORKER_START_S = 120.0
"""What a job's walltime must hold beyond one call: the worker's start and its handshake."""
_WALLTIME = re.compile(r"(?:(\d+)-)?(\d{1,3}):(\d{2})(?::(\d{2}))?")
_MEMORY = re.compile(r"(\d+(?:\.\d+)?)\s*(KB|MB|GB|TB|KiB|MiB|GiB|TiB)")
_UNITS = {"KB": 1e3, "MB": 1e6, "GB": 1e9, "TB": 1e12,
          "KiB": 2**10, "MiB": 2**20, "GiB": 2**30, "TiB": 2**40}


class ClusterSettings(BaseModel):
    """``[cluster]``: one batch job per Dask worker (one thread, one simulator call at once)."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)

    queue: str | None = Field(default=None, min_length=1,  # Slurm partition, PBS/LSF queue
                              validation_alias=AliasChoices("queue", "partition"))
    account: str | None = Field(default=None, min_length=1)  # Slurm account, PBS/LSF project
    cores: int = Field(default=1, ge=1, le=1024)  # per job: a run's threads x processes
    memory: str = Field(default="2GB", pattern=f"^{_MEMORY.pattern}$")  # per job, e.g. "4GB"
    walltime: str = Field(default="01:00:00", pattern=f"^{_WALLTIME.pattern}$")  # [D-]HH:MM[:SS]
    max_jobs: int = Field(default=4, ge=1, le=10000)  # jobs at once (ERT's MAX_RUNNING)
    # extra '#SBATCH ...' ('#PBS', '#BSUB') lines, without the prefix
    job_directives: tuple[str, ...] = Field(default=(), strict=False)
    prologue: tuple[str, ...] = Field(default=(), strict=False)  # shell lines, e.g. module load
    local_directory: str | None = None  # the worker's scratch folder on the compute node

    @property
    def walltime_s(self) -> float:
        """The walltime in seconds."""
        days, hours, minutes, seconds = _WALLTIME.fullmatch(self.walltime).groups()
        return (int(days or 0) * 86400 + int(hours) * 3600 + int(minutes) * 60
                + int(seconds or 0))

    @property
    def memory_bytes(self) -> float:
        """The memory per job in bytes."""
        number, unit = _MEMORY.fullmatch(self.memory).groups()
        return float(number) * _UNITS[unit]

    def job_kwargs(self, kind: ClusterKind) -> dict:
        """dask-jobqueue's keyword arguments for one single-threaded worker per job."""
        kwargs = {"cores": self.cores, "processes": 1, "memory": self.memory,
                  "walltime": self.walltime, "queue": self.queue,
                  "job_extra_directives": list(self.job_directives),
                  "job_script_prologue": list(self.prologue),
                  "worker_extra_args": ["--nthreads", "1"],
                  "local_directory": self.local_directory}
        if self.account is not None:
            kwargs["account" if kind is ClusterKind.SLURM else "project"] = self.account
        return {k: v for k, v in kwargs.items() if v is not None}


def cluster_problems(settings: ClusterSettings, timeout_s: float, cores_per_run: int,
                     where: str, peak_bytes: float | None = None) -> list[Problem]:
    """What would make a job unable to hold a call: a walltime shorter than the simulator's
    timeout plus :data:`WORKER_START_S`, fewer cores than a run uses, less memory than a
    run's measured peak (``peak_bytes``, when one is known). ``where``: the case file."""
    problems = []
    need = timeout_s + WORKER_START_S
    if settings.walltime_s < need:
        problems.append(Problem(
            f"{where} key 'cluster.walltime'",
            f"walltime {settings.walltime} ({settings.walltime_s:g} s) is shorter than one "
            f"call may take: the simulator's timeout_s {timeout_s:g} s plus "
            f"{WORKER_START_S:g} s for the worker to start",
            f"give walltime >= {_clock(need)} or lower simulator.timeout_s"))
    if settings.cores < cores_per_run:
        problems.append(Problem(
            f"{where} key 'cluster.cores'",
            f"{settings.cores} core(s) per job, but a run uses {cores_per_run} (simulator "
            "threads x processes)", f"give cores >= {cores_per_run}"))
    if peak_bytes is not None and settings.memory_bytes < 1.25 * peak_bytes:
        problems.append(Problem(
            f"{where} key 'cluster.memory'",
            f"memory {settings.memory} per job, but a run of this deck was measured at "
            f"{peak_bytes / 1e6:.0f} MB at its peak (a job needs 25 % more for its worker)",
            f"give memory >= {1.25 * peak_bytes / 1e9:.2f}GB"))
    return problems


def _clock(seconds: float) -> str:
    s = int(-(-seconds // 1))
    return f"{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"
