"""Curves and forecast of a campaign as a versioned artifact (reads run dirs; no simulator).

``<campaign>/curves/vN``: ``curves.parquet`` (one row per member, well, quantity and time:
``member`` (best, centre, truth or deck (the floor run), call-N, or draw-N for the N-th
posterior draw's run), ``call`` (from 1; 0 for the reference runs and the draws), then
:mod:`hmcore.simulation.curves`' columns), ``forecast.parquet``
(:func:`hmcore.simulation.forecast.forecast_table`) and ``forecast.json`` (member kind, the
caveat to print, member calls or draws, the posterior's figures, whether the floor run is
the truth). The forecast's members: an ES-MDA campaign's posterior ensemble; else the valid
runs of the posterior draws (:mod:`tasks.posterior`) when there are at least 2; else the best
calls by the campaign's objective. The report is drawn from it, so it survives the deletion
of the run dirs.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.calibration.loop import best_record
from hmcore.reporting.benchmark import case_truth
from hmcore.simulation.curves import read_curves
from hmcore.simulation.forecast import (
    DEFAULT_MEMBERS,
    MemberKind,
    choose_members,
    forecast_table,
)
from storage import ArtifactStore, ArtifactVersion, EvaluationJournal, code_version
from storage.posterior import POSTERIOR_STEP, journal_name
from tasks.reference import CENTRE, FLOOR


def _summary(run_dir: str | None) -> Path | None:
    if not run_dir or not Path(run_dir).is_dir():
        return None
    found = sorted(Path(run_dir).glob("*.SMSPEC"))
    return found[0] if found else None


def collect(store_root: str, campaign: str, reference: str | None,
            members: int = DEFAULT_MEMBERS) -> ArtifactVersion | None:
    """Build the ``curves`` artifact of ``campaign`` from its latest results, best case and
    reference journal (see the module docstring); None when no run left a summary."""
    store = ArtifactStore(store_root)
    results = store.latest(campaign, "results")
    case = store.latest(campaign, "case")
    if results is None or case is None:
        return None
    case_doc = case.read_json("case.json")
    wells = list(case_doc["wells"])
    stored = results.read_json("records.json")
    records, objective = stored["records"], stored.get("objective", "E")
    by_index = {r["index"]: r for r in records}
    chosen = choose_members(records, members, objective)  # the best call first
    best = best_record(records, objective)  # the campaign's best call (tasks.results)
    best_dir = store.latest(campaign, "best")
    frames, calls, skipped = [], {}, {}

    def add(member: str, call: int, summary: Path | None) -> pd.DataFrame | None:
        if summary is None:
            return None
        try:
            c = read_curves(summary, wells)
        except Exception as exc:  # a summary a dead or killed run left half-written
            skipped[member] = f"{summary}: {type(exc).__name__}: {exc}"
            return None
        frames.append(c.assign(member=member, call=call))
        return c

    def scored(record: dict | None) -> dict:
        """A run that ran to the end (scored; penalised runs too), else nothing to read."""
        return record if record and record.get("status") in ("COMPLETE", "INVALID") else {}

    if best is not None:
        archived = best_dir.path if best_dir is not None else None
        add("best", best["index"] + 1, _summary(best.get("run_dir")) or _summary(archived))
    refs = {}
    if reference and store.has_campaign(reference):
        refs = {r["index"]: r for r in EvaluationJournal(store, reference).rows()}
    # a latent case's floor runs the basis's image of the deck's fields, not a truth
    truth_known = case_truth(Path(case_doc["source"])) is not None and not case_doc.get("latent")
    floor = add("truth" if truth_known else "deck", 0,
                _summary(scored(refs.get(FLOOR)).get("run_dir")))
    add("centre", 0, _summary(scored(refs.get(CENTRE)).get("run_dir")))
    posterior = store.latest(campaign, POSTERIOR_STEP)
    draws = _valid_draws(store, campaign, posterior)
    kind, drawn = chosen.kind, None
    if chosen.kind is MemberKind.NEAR_BEST and len(draws) >= 2:  # the posterior's runs
        kind, drawn = MemberKind.LAPLACE, posterior.read_json("draws.json")
        for record in draws:
            c = add(f"draw-{record['index'] + 1}", 0, _summary(record.get("run_dir")))
            if c is not None:
                calls[record["index"] + 1] = c
    else:
        for index in chosen.indices:
            c = add(f"call-{index + 1}", index + 1, _summary(by_index[index].get("run_dir")))
            if c is not None:
                calls[index + 1] = c
    if not frames:
        return None
    table = forecast_table(calls, wells, floor if truth_known and floor is not None else None)
    curves = pd.concat(frames, ignore_index=True)[["member", "call", "well", "quantity", "days",
                                                   "value", "unit"]]
    doc = {"kind": kind.value, "caveat": kind.caveat, "objective": objective,
           "member_calls": [] if drawn else list(calls),
           "member_draws": list(calls) if drawn else [],
           "posterior": None if drawn is None else {
               k: drawn.get(k) for k in ("best_call", "asked", "kept", "tried", "inflation",
                                         "s2", "free")} | {"valid": len(calls)},
           "requested": members, "truth_known": truth_known,
           "truth_run": floor is not None and truth_known, "reference": reference,
           "skipped": skipped}
    return store.put_files(campaign, "curves", {"results": results.ref(),
                                                "reference": reference, "members": members,
                                                "posterior": posterior.ref() if posterior
                                                else None},
                           {"curves.parquet": curves, "forecast.parquet": table,
                            "forecast.json": doc}, code_version())


def stale(store_root: str, campaign: str) -> bool:
    """Whether ``campaign``'s latest curves were not drawn for its best call: made from
    other results, or by an hmflow that chose their best case and forecast members by E
    while the campaign's objective is another (its well panels' "best case" is then the
    lowest-E call, not the call the report names). A report rebuild collects them again
    (:func:`collect`, from the run directories)."""
    store = ArtifactStore(store_root)
    curves, results = store.latest(campaign, "curves"), store.latest(campaign, "results")
    if curves is None or results is None:
        return False
    doc = curves.read_json("forecast.json")
    objective = results.read_json("records.json").get("objective", "E")
    made_from = (curves.manifest.get("inputs") or {}).get("results")
    return doc.get("objective", "E") != objective or made_from != results.ref()


def _valid_draws(store: ArtifactStore, campaign: str, posterior: ArtifactVersion | None
                 ) -> list[dict]:
    """The valid runs of the ``posterior`` version's draws (:mod:`tasks.posterior`), in draw
    order; none without one."""
    if posterior is None:
        return []
    rows = EvaluationJournal(store, campaign, journal_name(posterior.version)).rows()
    return [r for r in rows if r.get("status") == "COMPLETE"]


collect_curves = task(name="collect-curves", cache_policy=NO_CACHE)(collect)
