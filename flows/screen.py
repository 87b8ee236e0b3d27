"""The screening flow (``hmflow screen``): which parameters move which responses, before a
match.

prepare the case -> the design (:mod:`hmcore.calibration.sensitivity`: OAT, or SALib's Morris
or Sobol') -> one journaled ``simulate`` task per point on the task runner the campaign uses
(a point already journaled is replayed, never simulated again: a killed screening resumes) ->
the responses of every call -> the ranked table, the tornado charts and report.html, stored as
one versioned artifact ``screening`` -> a new case file beside the old one with the parameters
that matter switched on (:mod:`hmcore.model.screened_case`).

A screening's name is bound to its settings like a campaign's (:func:`flows.campaign.
check_campaign_settings`): the same name with another case, method, budget or seed is refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from prefect import flow, get_run_logger

from flows.campaign import DEFAULT_STORAGE, check_campaign_settings
from flows.labels import Progress, tag_flow_run
from flows.refuse import USER_ERRORS, refused
from flows.runners import Runner
from flows.runners import task_runner as make_runner
from hmcore.calibration.calls import Job, replay_or_evaluate
from hmcore.calibration.objective import Objective
from hmcore.calibration.sensitivity import (
    ScreenMethod,
    analyse,
    choose,
    default_budget,
    default_screen_name,
    design,
    oat_centre,
    responses_of,
    screen_problems,
)
from hmcore.cases import load_case
from hmcore.model.screened_case import write_screened
from hmcore.reporting.screening import figures, ranking_markdown, report_html
from hmcore.scoring.evaluation import SCORING_VERSION
from storage import ArtifactStore, EvaluationJournal, code_version, sha256_json
from storage.lock import NameHeldError, NameKind, NameLock
from tasks.case import prepare_deck
from tasks.simulate import observation_set, simulate, simulate_parameters

SCREEN_VERSION = 1
"""Bumped when a screening's design or responses change meaning (stored in its settings)."""
STEP = "screening"
"""The artifact step of a screening's tables, charts, report and new case file."""


def jobs_of(actions: np.ndarray, space, workers: int) -> list[Job]:
    """One :class:`Job` per design point, in design order (call index = row)."""
    return [Job(i, space.to_values(a), tuple(float(x) for x in a), i % workers, "explore")
            for i, a in enumerate(actions)]


@flow(name="hmflow-screen", log_prints=True)
def screen_flow(case: str = "synthetic", method: str = "morris", budget: int | None = None,
                workers: int = 2, seed: int = 0, storage: str = DEFAULT_STORAGE,
                screen: str | None = None, task_runner: Runner = "threads",
                dask_address: str | None = None, centre: str = "prior") -> dict:
    """Screen ``case``'s scalar parameters with ``method`` (oat, morris, sobol) in ``budget``
    simulator calls (default: the method's, :func:`~hmcore.calibration.sensitivity.
    default_budget`), ``workers`` at a time; the same ``screen`` name resumes. ``centre``:
    where OAT starts, ``prior`` (the middle of the box) or ``deck`` (the deck's own values)."""
    logger = get_run_logger()
    try:
        storage = str(Path(storage).expanduser().resolve())
        loaded = load_case(case)
        problems = screen_problems(str(loaded.source), loaded.space.dim, method, budget, centre)
        if problems:
            raise ValueError("; ".join(problems))
    except USER_ERRORS as exc:
        return refused(exc)
    kind = ScreenMethod(method)
    budget = budget or default_budget(kind, loaded.space.dim)
    plan = design(kind, loaded.space, budget, seed, oat_centre(loaded, centre))
    name = screen or default_screen_name(loaded.name, method, seed)
    tag_flow_run("hmflow", "screen", f"case:{loaded.name}", f"method:{method}")
    lock = NameLock(storage, name, NameKind.CAMPAIGN)
    try:
        lock.acquire()
    except NameHeldError as exc:
        return refused(exc)
    try:
        case_version = prepare_deck(loaded, case, storage, name)
        try:
            check_campaign_settings(storage, name, {
                "case_artifact": case_version.ref(), "agent": f"screen-{method}", "seed": seed,
                "budget": budget, "screen_version": SCREEN_VERSION, "centre": plan.centre,
                "scoring_version": SCORING_VERSION, "objective": loaded.misfit.objective})
        except ValueError as exc:
            return refused(exc)
        journal = EvaluationJournal(ArtifactStore(storage), name)
        done = {r["index"]: r for r in journal.rows()}
        if done:
            logger.info(f"resuming screening {name}: {len(done)} calls already journaled")
        observations = observation_set(loaded)
        jobs = jobs_of(plan.actions, loaded.space, workers)
        progress = Progress(name, plan.calls)
        progress.update([r for i, r in done.items() if i < plan.calls])
        with make_runner(task_runner, workers, dask_address, loaded.cluster) as runner:

            def evaluate_batch(batch: list[Job]) -> list[dict]:
                # the whole design at once: the runner keeps its W workers busy (a fixed design
                # waits for no answer), and the progress moves call by call
                futures = [runner.submit(simulate, simulate_parameters(
                    loaded, job, storage, name, seed, f"screen-{method}", observations))
                    for job in batch]
                records = []
                for future in futures:
                    records.append(future.result())
                    progress.update(records[-1:])
                return records

            records = replay_or_evaluate(jobs, done, evaluate_batch, f"screen-{method}")
        return publish(storage, name, loaded, case_version.ref(), plan, records, observations)
    finally:
        lock.release()


def publish(storage: str, name: str, loaded, case_ref: dict, plan, records: list[dict],
            observations) -> dict:
    """Analyse the calls, store the screening artifact and write the new case file (once per
    stored screening: a rerun of a finished one finds its file and writes none)."""
    objective = Objective.of_case(loaded, observations)
    responses = responses_of(records, observations, objective)
    table = analyse(plan, responses)
    choice = choose(table, plan.method, loaded.space.names)
    skipped = [c for c in responses.columns if c not in set(table.response)]
    store = ArtifactStore(storage)
    inputs = {"case": case_ref, "design": plan.describe(), "screen_version": SCREEN_VERSION,
              "responses": sha256_json(responses.to_dict(orient="list"))}
    stored = store.reusable(name, STEP, inputs, code_version())
    if stored is not None:
        doc = stored.read_json("screening.json")
        if doc.get("case_file") and Path(doc["case_file"]).is_file():
            return {**doc, "report_html": str(stored.file("report.html")), "new_file": False}
    source = Path(loaded.source)
    header = [(f"written by `hmflow screen` (screening {name}, {plan.method.value}, "
               f"{plan.calls} calls) from {source.name}"),
              f"switched on: {', '.join(choice.chosen) or 'none'}; rule: {choice.rule}"]
    case_file = write_screened(source, loaded.space.parameters, choice.chosen, header)
    markdown = ranking_markdown(name, table, plan.method, plan.describe(), choice.rule,
                                choice.chosen, str(case_file), skipped, loaded.misfit.objective)
    pngs = figures(table, plan.method, loaded.misfit.objective)
    doc = {"screening": name, "method": plan.method.value, "design": plan.describe(),
           "chosen": list(choice.chosen), "dropped": list(choice.dropped),
           "rule": choice.rule, "ranked_on": choice.response, "case_file": str(case_file),
           "case_source": str(source), "skipped": skipped,
           "failed_calls": sum(1 for r in records if r.get("status") == "FAIL")}
    files = {"ranking.parquet": table, "ranking.md": markdown, "responses.parquet": responses,
             "screening.json": doc, "report.html": report_html(markdown, pngs),
             "case.screened.toml": case_file.read_text(encoding="utf-8"),
             **{f"figures/{k}": v for k, v in pngs.items()}}
    version = store.put_files(name, STEP, inputs, files, code_version())
    return {**doc, "report_html": str(version.file("report.html")), "new_file": True}


def overall_table(table: pd.DataFrame, response: str) -> pd.DataFrame:
    """The ranked rows of one response (the CLI prints the objective's)."""
    return table[table.response == response].reset_index(drop=True)
