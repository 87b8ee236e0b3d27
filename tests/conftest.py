"""Shared fixtures: the PUNQ-S3 benchmark data (read in place from ../shared/punqs3) and a
session-wide cache of real OPM Flow runs, so that the truth deck is simulated once per session.

The data is never copied into the repository; tests that need it skip with a clear reason when
it is absent. Tests that need a writable deck copy the three deck files into their tmp_path.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from prefect_processes import serve_prefect

from hmflow.server import wait_until_healthy

PUNQ_DIR = Path(__file__).resolve().parents[2] / "shared" / "punqs3"
PUNQ_DECK = PUNQ_DIR / "PUNQS3.DATA"
PUNQ_DECK_FILES = ("PUNQS3.DATA", "PUNQS3.GEO", "PUNQS3.PRP")
PUNQ_OBS_FULL = PUNQ_DIR / "punqs3_observed_full_history.csv"
PUNQ_OBS_STANDARD = PUNQ_DIR / "punqs3_observed_standard.csv"
PUNQ_HISTORY_END_DAYS = 2936.0
PUNQ_WELLS = ("PRO-1", "PRO-4", "PRO-5", "PRO-11", "PRO-12", "PRO-15")
TRUTH_VALUES = {"poro_mult": 1.0, "permx_mult": 1.0, "permy_mult": 1.0, "permz_mult": 1.0,
                "skin": 5.0}

# Prefect's ephemeral server logs "Stopping temporary server" at interpreter exit, after pytest
# has closed the stream its console handler writes to; without this, logging prints a
# "--- Logging error ---" traceback under the test summary (nothing failed).
logging.raiseExceptions = False

# `make test` runs two pytest-xdist workers. Each is its own process with its own Prefect
# servers, which must not share one PREFECT_HOME (one SQLite database, one profile file); and
# xdist sets COLUMNS=80 in a worker, which would fix the width of hmflow's consoles at import
# and override the width a test gives a command. Both set before any test module imports
# Prefect or hmflow.
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
if _WORKER:
    _HOME = Path(os.environ.get("PREFECT_HOME") or tempfile.mkdtemp(prefix="prefect-")) / _WORKER
    _HOME.mkdir(parents=True, exist_ok=True)
    os.environ["PREFECT_HOME"] = str(_HOME)
    os.environ.pop("COLUMNS", None)
    os.environ.pop("LINES", None)

# Prefect waits 20 s for its temporary server by default; with two simulations on the 2 cores
# the server's start (SQLite migrations) can take longer, and the test would fail for it.
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")

# The machine has 2 cores: never more than 2 simulations at once from this test session.
MAX_PARALLEL_SIMULATIONS = 2
SIMULATION_SLOTS = threading.BoundedSemaphore(MAX_PARALLEL_SIMULATIONS)


def _punq_missing() -> list[str]:
    needed = [*PUNQ_DECK_FILES, PUNQ_OBS_FULL.name, PUNQ_OBS_STANDARD.name]
    return [n for n in needed if not (PUNQ_DIR / n).is_file()]


def _opm_importable() -> bool:
    try:
        return (importlib.util.find_spec("opm.io") is not None
                and importlib.util.find_spec("opm.simulators") is not None)
    except ModuleNotFoundError:
        return False


PUNQ_SKIP_REASON = (f"PUNQ-S3 benchmark data not found in {PUNQ_DIR} (expected ../shared/punqs3 "
                    f"next to the repository; missing {_punq_missing()})")
requires_punq = pytest.mark.skipif(bool(_punq_missing()), reason=PUNQ_SKIP_REASON)
requires_opm = pytest.mark.skipif(not _opm_importable(),
                                  reason="OPM Python packages (opm, opm-simulators) not installed")


def pytest_collection_modifyitems(config, items):
    """Tests marked ``opm`` run the real simulator: skip them when OPM is not installed."""
    if _opm_importable():
        return
    skip = pytest.mark.skip(reason="OPM Python packages (opm, opm-simulators) not installed")
    for item in items:
        if item.get_closest_marker("opm") is not None:
            item.add_marker(skip)


def sha256_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def copy_punq_deck(dest: Path) -> Path:
    """Copy the deck's three files into ``dest`` (a writable temp copy); return the DATA path."""
    dest.mkdir(parents=True, exist_ok=True)
    for name in PUNQ_DECK_FILES:
        shutil.copyfile(PUNQ_DIR / name, dest / name)
    return dest / "PUNQS3.DATA"


def write_case_toml(path: Path, *, deck: Path = PUNQ_DECK, observed: Path = PUNQ_OBS_FULL,
                    name: str = "punqs3", history_end_days: float | None = PUNQ_HISTORY_END_DAYS,
                    extra_case: str = "", extra: str = "") -> Path:
    """Write a case TOML (deck/observed given as absolute paths unless relative on purpose)."""
    lines = ["[case]", f'name = "{name}"', f'deck = "{deck}"', f'observed = "{observed}"']
    if history_end_days is not None:
        lines.append(f"history_end_days = {history_end_days}")
    if extra_case:
        lines.append(extra_case.strip())
    text = "\n".join(lines) + "\n" + (("\n" + extra.strip() + "\n") if extra else "")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


class OpmRunCache:
    """Real OPM Flow runs of the PUNQ-S3 deck, one per set of parameter values, cached.

    Thread-safe: two threads asking for the same values share one run; at most
    MAX_PARALLEL_SIMULATIONS simulations run at once. Each run is its own subprocess
    (hmcore.simulation.simulator.OpmFlow).
    """

    def __init__(self, root: Path):
        from hmcore.eclipse.deck_info import DeckInfo
        from hmcore.model.parameters import ParameterSpace

        self.root = root
        self.info = DeckInfo.inspect(PUNQ_DECK)
        self.space = ParameterSpace.reference()
        self._lock = threading.Lock()
        self._key_locks: dict[tuple, threading.Lock] = {}
        self._done: dict[tuple, object] = {}

    @staticmethod
    def _key(values: dict[str, float]) -> tuple:
        return tuple(sorted((k, float(v)) for k, v in values.items()))

    def run(self, values: dict[str, float] | None = None):
        """SimulationResult of the deck with ``values`` applied ({} = the unmodified deck)."""
        from hmcore.model.run_deck import prepare_run_deck
        from hmcore.simulation.simulator import OpmFlow

        values = dict(values or {})
        key = self._key(values)
        with self._lock:
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        with key_lock:
            if key not in self._done:
                # no '=' in the path: OPM's option parser takes such a deck path for an option
                slug = "base" if not key else "__".join(f"{k}-{v:g}" for k, v in key)
                run_dir = self.root / re.sub(r"[^A-Za-z0-9_.-]", "_", slug)
                try:
                    deck = prepare_run_deck(PUNQ_DECK, values, self.space, run_dir, self.info)
                    with SIMULATION_SLOTS:
                        self._done[key] = OpmFlow(timeout_s=600).run(deck, run_dir)
                except Exception as exc:  # remember failures too: never rerun into the same dir
                    self._done[key] = exc
            result = self._done[key]
        if isinstance(result, Exception):
            raise result
        return result


@pytest.fixture(scope="session")
def punq_dir() -> Path:
    if _punq_missing():
        pytest.skip(PUNQ_SKIP_REASON)
    return PUNQ_DIR


@pytest.fixture(scope="session")
def punq_info(punq_dir):
    """DeckInfo of the shared PUNQ-S3 deck (parsed once per session)."""
    if not _opm_importable():
        pytest.skip("OPM Python packages (opm) not installed")
    from hmcore.eclipse.deck_info import DeckInfo

    return DeckInfo.inspect(PUNQ_DECK)


@pytest.fixture(scope="session")
def punq_case_toml(punq_dir, tmp_path_factory) -> Path:
    """The acceptance case: PUNQ-S3 deck + full measured history, fitted up to 2936 days."""
    return write_case_toml(tmp_path_factory.mktemp("punq_case") / "punqs3.toml")


@pytest.fixture(scope="session")
def punq_case(punq_case_toml, punq_info):
    from hmcore.cases import load_case

    return load_case(punq_case_toml)


@pytest.fixture(scope="session")
def opm_runs(punq_dir, tmp_path_factory) -> OpmRunCache:
    if not _opm_importable():
        pytest.skip("OPM Python packages (opm, opm-simulators) not installed")
    return OpmRunCache(tmp_path_factory.mktemp("opm_runs"))


@pytest.fixture(scope="session")
def truth_run(opm_runs):
    """One real OPM Flow run of the unmodified PUNQ-S3 truth deck (shared by all test files)."""
    return opm_runs.run({})


@pytest.fixture(scope="session")
def small_case(tmp_path_factory) -> Path:
    """``case.toml`` of the small synthetic case, written once per session (one real OPM run).

    :data:`hmcore.scenarios.synthetic_deck.SMALL_LAYOUT`, seed 0, case name
    ``synthetic-small``: the built-in case's reservoir, wells, gas cap, aquifer, shut-ins and
    noise on 10 x 10 x 5 cells over 3 years, a fifth of its simulation time. For tests of logic
    that need a real case (campaigns, reports, benchmarks, where a diagnosis is stored); what
    the built-in case is and what a diagnosis finds in it stay on the built-in case. Read only:
    a test that changes the case copies its folder first.
    """
    if not _opm_importable():
        pytest.skip("OPM Python packages (opm, opm-simulators) not installed")
    from hmcore.scenarios.synthetic import write_synthetic_case
    from hmcore.scenarios.synthetic_deck import SMALL_LAYOUT

    with SIMULATION_SLOTS:
        return write_synthetic_case(tmp_path_factory.mktemp("small-synthetic") / "case", 0,
                                    layout=SMALL_LAYOUT)


PREFECT_API_STARTUP_S = 300
"""How long the session's Prefect server may take to start (SQLite migrations on a busy
machine)."""


@pytest.fixture(scope="session")
def prefect_api(tmp_path_factory) -> Iterator[str]:
    """The URL of one Prefect API server for the session's command-line runs.

    `hmflow run`, `diagnose` and `bench` start a temporary Prefect server of their own unless
    ``PREFECT_API_URL`` is set (:mod:`hmflow.server`); a test that does not test that server
    passes ``cli_env(prefect_api)`` to the command instead and saves a server start per
    command. The same server as hmflow's temporary one (:func:`hmflow.server.temporary_api`:
    uvicorn with Prefect's app factory, on the session's PREFECT_HOME); stopped at the end of
    the session.
    """
    logs = tmp_path_factory.mktemp("prefect-api")
    app_dir = Path(importlib.util.find_spec("prefect").origin).parent.parent
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"http://127.0.0.1:{port}/api"
    env = {**{k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"},
           "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
           "PREFECT__SERVER_FINAL": "1"}
    with open(logs / "server.log", "wb") as log:  # the child keeps its own descriptor
        proc = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--app-dir", str(app_dir), "--factory",
             "prefect.server.api.server:create_app", "--host", "127.0.0.1", "--port", str(port),
             "--log-level", "error", "--lifespan", "on"],
            env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    try:
        try:
            wait_until_healthy(proc, url, PREFECT_API_STARTUP_S)
        except RuntimeError as e:
            pytest.fail(f"the session's Prefect server: {e}\n"
                        + (logs / "server.log").read_text(errors="replace")[-3000:])
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="session")
def prefect_server(tmp_path_factory) -> Iterator[dict]:
    """The session's one real `prefect server start` with its services and web UI (SQLite, a
    temporary PREFECT_HOME, a free loopback port), for the tests of the server itself: its
    scheduler and workers (test_deployments, test_prefect_server) and its UI in a browser
    (test_ui_browser); each uses its own work pool, deployments and run names. Yields its API
    URL, UI URL, home, env, root and log (:func:`prefect_processes.serve_prefect`)."""
    with serve_prefect(tmp_path_factory.mktemp("prefect-server"), ui=True) as server:
        yield server


@pytest.fixture
def restore_env():
    """In-process CLI calls set hmflow's Prefect defaults in os.environ (and mark the process
    quieted): undo both afterwards."""
    import hmflow.console as term  # here, not at the top: the worker's env is set first (above)

    saved, quieted = dict(os.environ), term._quieted
    yield
    os.environ.clear()
    os.environ.update(saved)
    term._quieted = quieted


def cli_env(api_url: str, **extra: str) -> dict[str, str]:
    """This process's environment for an `hmflow` subprocess that uses the session's Prefect
    server (:func:`prefect_api`) instead of starting its own, plus ``extra``."""
    return {**os.environ, "PREFECT_API_URL": api_url, **extra}
