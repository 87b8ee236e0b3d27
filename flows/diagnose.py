"""The diagnose flow: calibrate -> analyse residuals -> rank causes -> extend -> recalibrate ->
report. Simulations are Prefect tasks submitted together (``workers`` at a time), each run
journaled (:class:`tasks.diagnose.JournaledRuns`): a diagnosis killed and started again with
the same command replays the runs it had made and simulates only the others. Every step's
artifacts are stored as versioned artifacts of the campaign (steps ``diagnosis-calibration``,
``diagnosis-residuals``, ``diagnosis-ranking``, ``diagnosis-extension``,
``diagnosis-recalibration``, ``diagnosis-report``; the report holds ``diagnosis.json``). The
rounds and windows of :mod:`hmcore.diagnosis.rounds` store theirs the same way: a second
cause's round as ``diagnosis-2-calibration`` ... ``diagnosis-2-recalibration``, a later fitted
window as ``diagnosis-later-...`` (and its second round ``diagnosis-later-2-...``), a third
window (the origin rolled on) as ``diagnosis-later3-...``.

``diagnose_command`` is the ``hmflow diagnose`` command (register it on the CLI's Typer app).
"""

from __future__ import annotations

import dataclasses
import hashlib
import tempfile
from pathlib import Path
from typing import Annotated, Any, Optional

import pandas as pd
from prefect import flow, get_run_logger
from pydantic import Field

from flows.refuse import USER_ERRORS, input_problems, refused, scalar_problems
from flows.runners import Runner
from flows.runners import task_runner as make_runner
from hmcore.cases import BUILTIN_CASES, load_case
from hmcore.diagnosis import Diagnosis, DiagnosisSettings, budget_problem, diagnose_all, parse_kinds
from hmcore.scoring.evaluation import SCORING_VERSION
from storage import sha256_json
from tasks.case import fingerprint_differences, prepare_deck
from tasks.diagnose import JournaledRuns, diagnosis_journal, store_step
from tasks.results import report as campaign_report

DEFAULT_STORAGE = "./hmflow-storage"
STEPS = ("diagnosis-calibration", "diagnosis-residuals", "diagnosis-ranking",
         "diagnosis-extension", "diagnosis-recalibration", "diagnosis-report")


def default_campaign_name(case_name: str) -> str:
    return f"{case_name}-diagnosis"


def _content_hash(files: dict[str, Any]) -> str:
    """A hash of a step's files, so that new content is always a new version."""
    h = hashlib.sha256()
    for name in sorted(files):
        v = files[name]
        if isinstance(v, bytes):
            h.update(v)
        elif isinstance(v, str):
            h.update(v.encode())
        elif isinstance(v, dict):
            h.update(sha256_json(v).encode())
        else:  # DataFrame
            h.update(pd.util.hash_pandas_object(v, index=True).values.tobytes())
        h.update(name.encode())
    return h.hexdigest()


def campaign_start(store, name: str, case: str | None = None) -> tuple[str, dict[str, float]]:
    """The case and the calibrated parameters a diagnosis of the stored campaign ``name``
    starts from: its archived best, on the case it was run on (``case``: the one the user
    named, None: the campaign's own). A case whose files differ from the campaign's (hashes
    of the case file, deck, includes and history) is refused: the best parameters belong to
    the campaign's case. LookupError when the campaign has no archived best."""
    best, stored = store.latest(name, "best"), store.latest(name, "case")
    if best is None or stored is None:
        raise LookupError(f"no archived best case of campaign '{name}' in {store.root}: run "
                          f"`hmflow run --campaign {name}` first")
    own = str(stored.manifest.get("inputs", {}).get("case"))
    if own not in BUILTIN_CASES:  # a path as given then, maybe relative to another folder
        own = stored.read_json("case.json")["source"]
    case = case or own
    differ = fingerprint_differences(stored, load_case(case))
    if differ:
        raise ValueError(f"campaign '{name}' was calibrated on the case {own}; the case {case} "
                         f"differs from it ({', '.join(differ)}): its best parameters belong to "
                         f"the campaign's case - leave --case out, or diagnose {case} without "
                         "--from-campaign")
    return case, {k: float(v) for k, v in best.read_json("params.json").items()}


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


@flow(name="hmflow-diagnose", log_prints=True)
def diagnose_flow(case: str = "synthetic", storage: str = DEFAULT_STORAGE,
                  budget: Annotated[int, Field(ge=1)] | None = None,
                  campaign: str | None = None, workers: Annotated[int, Field(ge=1)] = 2,
                  calibrated: dict[str, float] | None = None,
                  initial: dict[str, float] | None = None,
                  settings: dict[str, Any] | None = None, task_runner: Runner = "threads",
                  dask_address: str | None = None, kinds: list[str] | None = None) -> dict:
    """Diagnose ``case``: what does the calibrated model get wrong, and what fixes it?

    Args:
        case: Case TOML file (an absolute path on the worker) or the built-in 'synthetic'.
        storage: Artifact store directory.
        budget: Cap on simulator calls, every one counted (None: as many as the steps need,
            about 40 + the number of candidate extensions); one that cannot cover the
            calibrated model and the ranking is refused before any simulation.
        campaign: Name the diagnosis is stored under (default CASE-diagnosis).
        workers: Simulations at once (the task runner's and the recalibration batches').
        calibrated: Skip the calibration of the case's own parameters (e.g. a campaign's
            best) and start from these values.
        initial: Start the calibration here instead of at the base model.
        settings: Overrides of :class:`DiagnosisSettings` fields (thresholds, kinds,
            confirm_top).
        task_runner: Where the simulations run: threads or dask (see :mod:`flows.runners`).
        dask_address: Scheduler of an existing Dask cluster (default DASK_ADDRESS, else a
            local cluster of `workers` processes).
        kinds: Families of candidate extensions to search (default all; see
            :data:`hmcore.diagnosis.KINDS`).

    Returns the campaign, the ranked causes, the selected extension, the gain,
    ``diagnosis_path`` (the stored ``diagnosis.json``) and the simulations made.
    """
    logger = get_run_logger()
    storage = str(Path(storage).expanduser().resolve())
    try:  # bad input from the UI or the API: one clear line, no traceback, no simulation
        problems = input_problems(task_runner=task_runner)
        if problems:
            raise ValueError("; ".join(problems))
        loaded = load_case(case)
        problems = scalar_problems(loaded)
        if problems:
            raise ValueError("; ".join(problems))
        opts = dict(settings or {})
        unknown = sorted(set(opts) - {f.name for f in dataclasses.fields(DiagnosisSettings)})
        if unknown:
            raise ValueError(f"settings: unknown field(s) {unknown} (fix: use fields of "
                             "hmcore.diagnosis.DiagnosisSettings)")
        if kinds is not None:
            opts["kinds"] = parse_kinds(kinds, "kinds")
        diagnosis_settings = DiagnosisSettings(**{**opts, "budget": budget, "workers": workers})
        problem = budget_problem(loaded, diagnosis_settings, calibrated is not None, "budget")
        if problem:
            raise ValueError(str(problem))
    except USER_ERRORS as exc:
        return refused(exc)
    campaign = campaign or default_campaign_name(loaded.name)
    case_version = prepare_deck(loaded, case, storage, campaign)
    # the case by its content: other code stores the same files as another version number
    case_content = {k: v for k, v in case_version.ref().items() if k != "version"}
    journal = diagnosis_journal({"case": case_content,
                                 "settings": diagnosis_settings.to_dict(),
                                 "calibrated": calibrated, "initial": initial,
                                 "scoring_version": SCORING_VERSION})
    previous: dict[str, Any] = {"case": case_version.ref()}
    versions = {}

    def store(step: str, files: dict[str, Any]):
        inputs = {**previous, "settings": diagnosis_settings.to_dict(),
                  "content": _content_hash(files)}
        v = store_step(storage, campaign, step, inputs, files)
        previous.clear()
        previous.update({"case": case_version.ref(), "previous": v.ref()})
        versions[step] = v
        return v

    with make_runner(task_runner, workers, dask_address, loaded.cluster) as runner:
        runs = JournaledRuns(storage, campaign, journal, runner)
        if runs.journaled:
            logger.info(f"resuming the diagnosis {campaign}: {runs.journaled} runs already "
                        f"journaled ({runs.journal.directory}), replayed, not simulated")
        out = diagnose_all(loaded, runs, calibrated=calibrated, initial=initial,
                           settings=diagnosis_settings, log=logger.info,
                           on_step=lambda name, d: store(f"diagnosis-{name}",
                                                         step_files(name, d)))
    doc = out.document
    with tempfile.TemporaryDirectory(prefix="hmflow-diagnosis-") as tmp:
        out.report(Path(tmp))
        report_files = {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir())}
    rep = store("diagnosis-report", report_files)
    path = rep.file("diagnosis.json")
    whole = campaign_report(storage, campaign)  # the campaign's report, with the diagnosis
    sel = doc["selected"]
    logger.info(f"diagnosis of {loaded.name}: {doc['verdict']}")
    return {"campaign": campaign, "storage": storage, "causes": doc["causes"],
            "selected": sel, "verdict": doc["verdict"], "gain": doc["gain"],
            "accepted": doc.get("accepted", []), "answer": doc.get("answer"),
            "diagnosis_path": str(path), "report_path": str(rep.file("report.md")),
            "campaign_report_path": str(whole.file("report.md")),
            "artifacts": {k: v.ref() for k, v in versions.items()},
            "simulations": doc["cost"]["simulations"]}


def step_files(name: str, d: Diagnosis) -> dict[str, Any]:
    """The files stored for step ``name`` of a round (``calibration``, ``2-ranking``,
    ``later-recalibration``, ...; see :mod:`hmcore.diagnosis.rounds`)."""
    step = name.rsplit("-", 1)[-1]
    if step == "calibration":
        return {"calibration.json": d.calibration,
                "responses.parquet": d.base.responses.reset_index(drop=True)}
    if step == "residuals":
        return {"residuals.json": d.residuals, "observations.parquet": d.obs.rows}
    if step == "ranking":
        return {"ranking.json": d.ranking,
                "sensitivities.parquet": pd.DataFrame({k: v for k, v in d.sensitivity.items()})}
    if step == "extension":
        return {"extension.json": d.extension}
    files = {"recalibration.json": d.recalibration}
    for cid, run in d.confirmed_runs.items():
        if run.responses is not None:
            files[f"responses_{_safe(cid)}.parquet"] = run.responses.reset_index(drop=True)
    return files


# ============================================================================ CLI
def print_diagnosis(result: dict, console=None, most: int = 8) -> None:
    """Print the ranked causes, the selected extension, the gain and the report's path."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()

    def num(v, digits=5):
        return "n/a" if v is None else f"{v:.{digits}g}"

    t = Table(title="Ranked causes (best first; 'none' marks the noise level)")
    for col in ("rank", "kind", "wells", "layers", "score", "chi2", "evidence"):
        t.add_column(col, justify="right" if col in ("rank", "score", "chi2") else "left")
    for n, c in enumerate(result["causes"][:most], 1):
        t.add_row(str(n), c["kind"], ", ".join(c["wells"]) or "-",
                  ", ".join(map(str, c["layers"])) or "-", num(c["score"], 3), num(c["chi2"], 4),
                  c.get("evidence", ""))
    console.print(t)
    sel = result["selected"]
    console.print(f"selected: [bold]{sel['kind']}[/] ({sel['id']}) - {sel['description']}"
                  if sel else "selected: [bold]none[/]")
    for a in result.get("accepted", [])[1:]:  # forward selection: the second cause
        g = a["gain"]
        console.print(f"and, with it in the model: [bold]{a['kind']}[/] ({a['id']}) - "
                      f"{a['description']} (fitted E {num(g['fit_before'])} -> "
                      f"{num(g['fit_after'])}, held-back E {num(g['heldout_before'])} -> "
                      f"{num(g['heldout_after'])})")
    console.print(result["verdict"], highlight=False)
    a = result.get("answer")
    if a and a.get("explanations"):  # the answer by the evidence (issue 46)
        at = Table(title="By the evidence: " + ("one cause dominates" if a["kind"] == "single"
                                                else "the data cannot separate these"))
        for col in ("explanation", "weight", "log evidence", "fitted SSR", "held-back SSR"):
            at.add_column(col, justify="left" if col == "explanation" else "right")
        for x in a["explanations"][:most]:
            at.add_row(x["id"] + (" *" if x["id"] in a["members"] else ""),
                       f"{x['weight']:.3f}", f"{x['log_evidence']:.1f}", num(x["ssr_fit"], 6),
                       num(x["ssr_heldout"], 6))
        console.print(at)
        for sep in a.get("separations") or []:
            console.print(f"to separate them: {sep['sentence']}", highlight=False)
    g = result["gain"]
    gt = Table(title="Gain (misfit E)")
    for col in ("history", "before", "after"):
        gt.add_column(col, justify="left" if col == "history" else "right")
    gt.add_row("fitted", num(g["fit_before"]), num(g["fit_after"]))
    gt.add_row("held back", num(g["heldout_before"]), num(g["heldout_after"]))
    console.print(gt)
    console.print(f"diagnosis: {result['diagnosis_path']}")
    console.print(f"report:    {result['report_path']}")
    if result.get("campaign_report_path"):
        console.print(f"campaign report (rebuild with `hmflow report --campaign "
                      f"{result['campaign']}`): {result['campaign_report_path']}")


def diagnose_command(case: str = "synthetic", storage: Path = Path(DEFAULT_STORAGE),
                     budget: Optional[int] = None, workers: int = 2,
                     campaign: Optional[str] = None,
                     calibrated: Optional[dict[str, float]] = None, console=None,
                     task_runner: Runner = "threads", dask_address: Optional[str] = None,
                     kinds: Optional[list[str]] = None,
                     settings: Optional[dict[str, Any]] = None) -> dict:
    """``hmflow diagnose``: run the flow with ``workers`` simulations at a time and print the
    ranked causes, the gain and the path of diagnosis.json. Returns the flow's result
    (``settings``: overrides of :class:`DiagnosisSettings`, as the flow takes them)."""
    result = diagnose_flow(case=str(case), storage=str(Path(storage).resolve()), budget=budget,
                           campaign=campaign, workers=workers, calibrated=calibrated,
                           task_runner=task_runner, dask_address=dask_address, kinds=kinds,
                           settings=settings)
    print_diagnosis(result, console)
    return result
