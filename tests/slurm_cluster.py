"""A real one-node Slurm for the tests (issue 43): Debian's ``slurm-wlm`` and ``munge``
(``make install-test`` installs them as root), with a slurm.conf of our own for this host,
munged, slurmctld and slurmd started in a temporary folder and stopped afterwards.

The configuration needs no cgroup (``proctrack/linuxproc``, ``task/none``), schedules cores
and memory (``select/cons_tres``, ``CR_Core_Memory``) on one node of 2 CPUs and the machine's
real memory (``slurmd -C``), and writes each finished job to a job completion file
(``jobcomp/filetxt``) that ``sacct -c`` reads: there is no slurmdbd. Clients find it through
``SLURM_CONF`` (:attr:`Slurm.env`). Every daemon is started by us and stopped by its pid.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "squeue", "scancel", "sacct", "sinfo")
START_TIMEOUT_S = 60


def missing() -> list[str]:
    """The Slurm and munge programs this machine lacks (empty: it can run a one-node Slurm)."""
    return [p for p in DAEMONS + CLIENTS if shutil.which(p) is None]


def skip_reason() -> str | None:
    """Why a one-node Slurm cannot run here, or None."""
    if missing():
        return (f"Slurm is not installed ({', '.join(missing())} missing): `make install-test` "
                "as root installs Debian's slurm-wlm and munge")
    if os.geteuid() != 0:
        return "the one-node Slurm of the tests runs its daemons as root"
    return None


@dataclass(frozen=True)
class Slurm:
    """A running one-node Slurm: its folder, configuration, node and the clients' env."""

    root: Path
    conf: Path
    node: str
    cpus: int
    env: dict[str, str]

    def run(self, *args: str, timeout: float = 30) -> str:
        """A Slurm client's output (``sacct``, ``squeue``, ``scancel``...)."""
        done = subprocess.run(list(args), env=self.env, capture_output=True, text=True,
                              timeout=timeout, check=True)
        return done.stdout

    def finished_jobs(self) -> dict[str, dict[str, str]]:
        """Finished jobs as ``sacct -c`` lists them: job id -> name, state, node."""
        out = self.run("sacct", "-c", "--parsable2", "--noheader",
                       "--format=JobID,JobName,State,NodeList")
        jobs = {}
        for line in out.splitlines():
            job, name, state, node = (line.split("|") + ["", "", "", ""])[:4]
            if job:
                jobs[job] = {"name": name, "state": state, "node": node}
        return jobs

    def running_jobs(self) -> list[str]:
        """Ids of the jobs in the queue (pending or running)."""
        return self.run("squeue", "--noheader", "--format=%i").split()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _real_memory_mb() -> int:
    out = subprocess.run(["slurmd", "-C"], capture_output=True, text=True, timeout=30,
                         check=True).stdout
    return int(re.search(r"RealMemory=(\d+)", out).group(1))


def _conf(root: Path, node: str, cpus: int, memory_mb: int) -> str:
    return f"""ClusterName=hmflowtest
SlurmctldHost={node}(127.0.0.1)
SlurmUser=root
SlurmdUser=root
SlurmctldPort={_free_port()}
SlurmdPort={_free_port()}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={root}/munge/munge.socket
StateSaveLocation={root}/state
SlurmdSpoolDir={root}/spool
SlurmctldPidFile={root}/slurmctld.pid
SlurmdPidFile={root}/slurmd.pid
SlurmctldLogFile={root}/slurmctld.log
SlurmdLogFile={root}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
JobCompType=jobcomp/filetxt
JobCompLoc={root}/jobcomp.txt
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
ReturnToService=2
MpiDefault=none
KillWait=5
NodeName={node} CPUs={cpus} RealMemory={memory_mb} State=UNKNOWN
PartitionName=debug Nodes={node} Default=YES MaxTime=INFINITE State=UP
"""


def _pid(path: Path) -> int | None:
    try:
        return int(path.read_text().strip())
    except (OSError, ValueError):
        return None


def _stop(pid_file: Path) -> None:
    pid = _pid(pid_file)
    if pid is None:
        return
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.2)
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


@contextmanager
def one_node_slurm(cpus: int = 2) -> Iterator[Slurm]:
    """munged, slurmctld and slurmd on this host in a fresh folder (short: the munge socket's
    path must fit a Unix socket's 108 bytes); stopped, and the folder removed, afterwards."""
    root = Path(tempfile.mkdtemp(prefix="slurm-", dir="/tmp"))
    node = socket.gethostname().split(".")[0]
    for sub in ("state", "spool", "munge"):
        (root / sub).mkdir()
    os.chmod(root / "munge", 0o700)
    conf = root / "slurm.conf"
    conf.write_text(_conf(root, node, cpus, _real_memory_mb()))
    env = {**os.environ, "SLURM_CONF": str(conf)}
    pid_files = [root / "munge" / "munged.pid", root / "slurmctld.pid", root / "slurmd.pid"]
    try:
        # --force: munged as root, in a folder it does not own (each daemon forks and exits)
        subprocess.run(["munged", "--force", f"--socket={root}/munge/munge.socket",
                        f"--pid-file={pid_files[0]}", f"--log-file={root}/munge/munged.log",
                        f"--seed-file={root}/munge/seed"], env=env, check=True, timeout=30,
                       capture_output=True)
        subprocess.run(["slurmctld", "-f", str(conf), "-i"], env=env, check=True, timeout=30,
                       capture_output=True)
        subprocess.run(["slurmd", "-f", str(conf)], env=env, check=True, timeout=30,
                       capture_output=True)
        slurm = Slurm(root, conf, node, cpus, env)
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            try:
                state = slurm.run("sinfo", "--noheader", "--format=%T").split()
            except subprocess.SubprocessError:
                state = []
            if state and state[0] in ("idle", "mixed", "allocated"):
                break
            if time.monotonic() > deadline:
                logs = "\n".join(p.read_text(errors="replace")[-2000:]
                                 for p in (root / "slurmctld.log", root / "slurmd.log")
                                 if p.exists())
                raise RuntimeError(f"the one-node Slurm did not come up in {START_TIMEOUT_S} "
                                   f"s (sinfo: {state}):\n{logs}")
            time.sleep(0.5)
        yield slurm
    finally:
        try:  # jobs left running (a failed test): cancelled before the daemons stop
            subprocess.run(["scancel", "--full", "--user", "root"], env=env, timeout=30,
                           capture_output=True, check=False)
        except (OSError, subprocess.SubprocessError):
            pass
        for pid_file in reversed(pid_files):
            _stop(pid_file)
        shutil.rmtree(root, ignore_errors=True)
