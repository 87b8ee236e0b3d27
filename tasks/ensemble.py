"""The steps of an ensemble run (``flows.ensemble``) as thin Prefect tasks over
:mod:`hmcore.fields` and the store (layout: :mod:`storage.ensemble`).

* :func:`prepare_ensemble`: the grid, the data the smoother sees, the parameters' locations;
* :func:`prior_step`: the prior ensemble drawn (or read from the user's GRDECL files) and
  stored, once: a rerun reuses the stored version and draws nothing;
* :func:`member_jobs` and :func:`submit_members`: one journaled ``simulate`` task per member
  not yet journaled (:mod:`tasks.simulate`), the member's fields included by
  :class:`~hmcore.fields.members.MemberSimulator`;
* :func:`update_step`: ES-MDA's update from the members' records, the next ensemble stored;
* :func:`forecast_step`: P90/P50/P10 of the prior and the posterior, every member's value, and
  what each round of runs gave; every prior and posterior member's curves and every member's
  misfit per round, which the report (:mod:`tasks.ensemble_report`) draws.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.calibration.calls import Job
from hmcore.fields.assimilation import (
    draw_ensemble,
    iteration_summary,
    misfit,
    smoother_data,
    update,
    well_locations,
)
from hmcore.fields.forecast import ensemble_forecast, headline, member_values
from hmcore.fields.grid import FieldGrid, read_grid
from hmcore.fields.layout import Layout
from hmcore.fields.members import MemberSimulator, ensemble_matrix, ensemble_table
from hmcore.fields.smoother import Observations, TooFewRealizations
from hmcore.model.case import Case
from hmcore.scoring.evaluation import SCORING_VERSION, simulator_for
from hmcore.scoring.observations import ObservationSet
from hmcore.simulation.curves import read_curves
from storage import (
    ArtifactStore,
    ArtifactVersion,
    EvaluationJournal,
    code_version,
    sha256_json,
    to_jsonable,
)
from storage.ensemble import (
    CURVES_FILE,
    ENSEMBLE_DOC,
    ENSEMBLE_FILE,
    ENSEMBLE_RUNS,
    FORECAST_STEP,
    GRID_FILE,
    MISFIT_FILE,
    ensemble_step,
    member_journal,
    member_run_name,
)
from tasks.simulate import Destination, simulate, simulate_parameters

AGENT = "ensemble"
"""The ``agent`` of a member's record."""


@dataclass(frozen=True, eq=False)
class EnsembleSetup:
    """What every step of a run shares: the deck's ``grid``, the ``observations`` (the rows
    and noise of the fitted history, whose whitened residuals each record keeps), the
    ``data`` the smoother sees (:func:`hmcore.fields.assimilation.smoother_data`), the
    parameters' ``layout`` and their ``locations`` (x, y per column, for distance
    localisation)."""

    grid: FieldGrid
    observations: ObservationSet
    data: Observations
    layout: Layout
    locations: np.ndarray


def ensemble_settings(case: Case, case_version: ArtifactVersion, deck_files: dict) -> dict:
    """What an ensemble run's name is bound to: the case as stored, every file its deck
    reads, the fields with their priors, the scalars and the ``[ensemble]`` section."""
    return {"kind": "ensemble", "case_artifact": case_version.ref(), "deck_files": deck_files,
            "fields": [f.model_dump(mode="json", by_alias=True) for f in case.fields],
            "scalars": case.space.names, "ensemble": case.ensemble.model_dump(mode="json"),
            "scoring_version": SCORING_VERSION}


@task(name="prepare-ensemble", cache_policy=NO_CACHE)
def prepare_ensemble(case: Case) -> EnsembleSetup:
    """The grid (opm.io), the fitted history's rows with their noise, and the locations."""
    grid = read_grid(case.deck)
    observations = ObservationSet.from_case(case)
    rows = observations.vector_index("fit")
    wells = observations.rows.well.to_numpy()[rows]
    xy = well_locations(grid, {w.name: w.connections for w in case.info.wells.values()})
    layout = Layout(tuple(f.name for f in case.fields), tuple(case.space.names), grid.n_active)
    return EnsembleSetup(grid, observations, smoother_data(list(wells), xy), layout,
                         layout.locations(grid))


@task(name="prior", cache_policy=NO_CACHE)
def prior_step(case: Case, setup: EnsembleSetup, storage: str, campaign: str,
               case_version: ArtifactVersion) -> ArtifactVersion:
    """The prior ensemble (``ensemble-00``): drawn or read, with its seeds and the grid (its
    dims and active cells, where the report draws a parameter's cell); reused, not drawn
    again, when stored from the same case and fields."""
    spec = case.ensemble
    inputs = {"case": case_version.ref(), "size": spec.size, "seed": spec.seed,
              "fields": [f.model_dump(mode="json", by_alias=True) for f in case.fields],
              "scalars": case.space.names}

    def write(directory: Path) -> None:
        prior = draw_ensemble(case.fields, setup.grid, spec.size, case.space.names, spec.seed)
        ensemble_table(prior.X, prior.layout).to_parquet(directory / ENSEMBLE_FILE)
        pd.DataFrame({"active": setup.grid.active.astype(np.int64)}).to_parquet(
            directory / GRID_FILE)
        _write_doc(directory, {"iteration": 0, "members": spec.size,
                               "active": list(range(spec.size)), "seeds": dict(prior.seeds),
                               "sources": dict(prior.sources), "dims": list(setup.grid.dims),
                               **_layout_doc(prior.layout)})

    return ArtifactStore(storage).put(campaign, ensemble_step(0), inputs, write, code_version())


def member_jobs(case: Case, ensemble: ArtifactVersion, iteration: int,
                layout: Layout) -> list[Job]:
    """One job per member still in ``ensemble`` (members left out have NaN rows): its
    scalar parameters' values (the fields come from the stored ensemble), phase ``iNN``."""
    X = ensemble_matrix(ensemble.read_parquet(ENSEMBLE_FILE), layout)
    _, scalars = layout.split(X)
    jobs = []
    for m in np.flatnonzero(np.isfinite(X).all(axis=1)):
        u = np.array([scalars[n][m] for n in layout.scalars], float)
        values = case.space.to_values(u) if layout.scalars else {}
        jobs.append(Job(int(m), values, tuple(float(x) for x in u), 0, f"i{iteration:02d}"))
    return jobs


def submit_members(runner, case: Case, setup: EnsembleSetup, ensemble: ArtifactVersion,
                   iteration: int, jobs: list[Job], storage: str, campaign: str) -> list:
    """Submit, on the started task ``runner``, the journaled ``simulate`` task of every job
    not yet journaled; returns the futures (a journaled member is never simulated again)."""
    journal = EvaluationJournal(ArtifactStore(storage), campaign, member_journal(iteration))
    done = set(journal.indices())
    destination = Destination(journal=member_journal(iteration), runs=ENSEMBLE_RUNS,
                              run_name=member_run_name(iteration))
    inner = simulator_for(case)
    futures = []
    for job in jobs:
        if job.index in done:
            continue
        simulator = MemberSimulator(inner, ensemble.file(ENSEMBLE_FILE), job.index,
                                    case.fields, setup.grid, setup.layout,
                                    case.info.keyword_names)
        futures.append(runner.submit(simulate, simulate_parameters(
            case, job, storage, campaign, case.ensemble.seed, AGENT, setup.observations,
            destination, simulator)))
    return futures


def member_records(storage: str, campaign: str, iteration: int) -> dict[int, dict]:
    """The journaled records of ensemble ``iteration``'s members, by member."""
    journal = EvaluationJournal(ArtifactStore(storage), campaign, member_journal(iteration))
    return {r["index"]: r for r in journal.rows()}


def with_residuals(records: dict[int, dict], observations: ObservationSet) -> dict[int, dict]:
    """The records with ``residuals``: the whitened residual vector of the fitted history
    (:meth:`~hmcore.scoring.observations.ObservationSet.whiten`) from the simulated value of
    every row a record keeps (``simulated``); None for a failed run."""
    observed = observations.rows.observed.to_numpy(float)
    sigma = observations.rows.sigma.to_numpy(float)
    out = {}
    for m, r in records.items():
        sim = r.get("simulated")
        residuals = None
        if r.get("status") != "FAIL" and sim is not None and len(sim) == len(observed):
            values = np.array([np.nan if v is None else v for v in sim], float)
            residuals = observations.whiten((values - observed) / sigma, "fit").tolist()
        out[m] = {**r, "residuals": residuals}
    return out


@task(name="update", cache_policy=NO_CACHE)
def update_step(case: Case, setup: EnsembleSetup, ensemble: ArtifactVersion,
                records: dict[int, dict], iteration: int, storage: str,
                campaign: str) -> ArtifactVersion | str:
    """ES-MDA update ``iteration`` (0-based) of ``ensemble`` with its members' ``records``,
    stored as ``ensemble-<iteration + 1>``; below the ensemble's ``min_realizations``, nothing
    stored and the reason returned (one line: :class:`TooFewRealizations`'s). The same ensemble and records give the same update, so
    a resumed run reuses the stored version."""
    X = ensemble_matrix(ensemble.read_parquet(ENSEMBLE_FILE), setup.layout)
    records = with_residuals(records, setup.observations)
    try:
        result = update(X, records, setup.data, iteration, case.ensemble, setup.locations)
    except TooFewRealizations as exc:  # the flow's one line, not a failed task's traceback
        return str(exc)
    data = {str(m): {k: r.get(k) for k in ("status", "residuals")} for m, r in records.items()}
    inputs = {"previous": ensemble.ref(), "iteration": iteration,
              "ensemble": case.ensemble.model_dump(mode="json"), "records": sha256_json(data)}

    def write(directory: Path) -> None:
        ensemble_table(result.ensemble, setup.layout).to_parquet(directory / ENSEMBLE_FILE)
        _write_doc(directory, {"iteration": iteration + 1, "members": int(X.shape[0]),
                               "active": np.flatnonzero(result.active).tolist(),
                               "left_out_now": list(result.left_out), "alpha": result.alpha,
                               "constant_data": list(result.constant),
                               "batches": result.batches,
                               "update_seconds": round(result.seconds, 4),
                               **_layout_doc(setup.layout)})

    return ArtifactStore(storage).put(campaign, ensemble_step(iteration + 1), inputs, write,
                                      code_version())


@task(name="forecast", cache_policy=NO_CACHE)
def forecast_step(case: Case, observations: ObservationSet, storage: str, campaign: str,
                  iterations: int, planned: dict[int, list[int]]) -> ArtifactVersion:
    """The forecast of the prior (the runs of ``ensemble-00``) and the posterior (the runs of
    ``ensemble-<iterations>``) and the summary of every round of runs (``planned``: the
    members each round was to run); beside them the members' curves
    (:func:`member_curves`) and misfits (:func:`member_misfits`), so that the report reads
    the store and no run directory."""
    wells = sorted(case.info.wells)
    store = ArtifactStore(storage)
    rounds = {i: member_records(storage, campaign, i) for i in range(iterations + 1)}
    scored = {i: with_residuals(r, observations) for i, r in rounds.items()}
    curves, skipped = {}, {}
    for name, i in (("prior", 0), ("posterior", iterations)):
        curves[name] = {}
        for m, r in sorted(rounds[i].items()):
            summary = summary_file(r.get("run_dir")) if r.get("status") != "FAIL" else None
            if summary is None:
                continue
            try:
                curves[name][m] = read_curves(summary, wells)
            except Exception as exc:  # noqa: BLE001 - opm.io raises many kinds on a half-written summary
                skipped[f"{name} {m}"] = f"{summary}: {type(exc).__name__}: {exc}"
    table = ensemble_forecast(curves, wells)
    updates = [store.latest(campaign, ensemble_step(i)).read_json(ENSEMBLE_DOC)
               for i in range(1, iterations + 1)]
    doc = {"iterations": [iteration_summary(i, planned[i], scored[i])
                          for i in range(iterations + 1)],
           "updates": [{k: u.get(k) for k in ("iteration", "alpha", "left_out_now",
                                              "constant_data", "update_seconds",
                                              "batches")} for u in updates],
           "runs": sum(len(r) for r in rounds.values()),
           "failed": sum(1 for r in rounds.values() for x in r.values()
                         if x.get("status") == "FAIL"),
           "headline": headline(table), "skipped": skipped}
    inputs = {"records": sha256_json({str(i): sorted((m, r.get("finished_at")) for m, r in
                                                rounds[i].items()) for i in rounds}),
              "iterations": iterations}
    return store.put_files(campaign, FORECAST_STEP, inputs,
                           {"forecast.parquet": table, "members.parquet":
                            member_values(curves, wells), "summary.json": doc,
                            CURVES_FILE: member_curves(curves),
                            MISFIT_FILE: member_misfits(scored)}, code_version())


def member_curves(curves: dict[str, dict[int, pd.DataFrame]]) -> pd.DataFrame:
    """Every member's curves, whole schedule, in one table: ``ensemble`` (prior, posterior),
    ``member`` and :func:`~hmcore.simulation.curves.read_curves`' columns (values float32)."""
    frames = [c.assign(ensemble=e, member=m) for e, by_member in curves.items()
              for m, c in sorted(by_member.items())]
    columns = ["ensemble", "member", "well", "quantity", "days", "value", "unit"]
    if not frames:
        return pd.DataFrame({c: pd.Series(dtype=float if c in ("days", "value") else
                                          int if c == "member" else str) for c in columns})
    out = pd.concat(frames, ignore_index=True)[columns]
    for c in ("ensemble", "well", "quantity", "unit"):
        out[c] = out[c].astype("category")
    return out.astype({"member": np.int32, "value": np.float32})


def member_misfits(scored: dict[int, dict[int, dict]]) -> pd.DataFrame:
    """Every member's data misfit (:func:`~hmcore.fields.assimilation.misfit`, NaN for a
    failed run) in every round of runs: ``iteration`` (0 the prior's runs, the last the
    posterior's), ``member``, ``status``, ``failure``, ``misfit``."""
    rows = [{"iteration": i, "member": m, "status": str(r.get("status")),
             "failure": r.get("failure") or "", "misfit": misfit(r)}
            for i, records in sorted(scored.items()) for m, r in sorted(records.items())]
    return pd.DataFrame(rows, columns=["iteration", "member", "status", "failure", "misfit"])


def summary_file(run_dir: str | None) -> Path | None:
    """The summary (``*.SMSPEC``) a run left in ``run_dir``; None when there is none."""
    found = sorted(Path(run_dir).glob("*.SMSPEC")) if run_dir and Path(run_dir).is_dir() else []
    return found[0] if found else None


def _layout_doc(layout: Layout) -> dict:
    return {"fields": list(layout.fields), "scalars": list(layout.scalars),
            "n_active": layout.n_active}


def _write_doc(directory: Path, doc: dict) -> None:
    (directory / ENSEMBLE_DOC).write_text(json.dumps(to_jsonable(doc), indent=2) + "\n")
