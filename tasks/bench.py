"""Benchmark task: the consolidation of every (method, seed) campaign into Parquet, a Markdown
table and a plot (no simulator there; the reference runs are in :mod:`tasks.reference`)."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE

from hmcore.reporting import benchmark
from hmcore.scoring.metrics import worst_well_cmatch
from hmcore.calibration.objective import Objective
from storage import ArtifactStore, EvaluationJournal, code_version
from tasks.noise import NOISE_STEP


@task(name="consolidate-benchmark", cache_policy=NO_CACHE)
def consolidate_bench(store_root: str, bench: str, campaigns: dict[str, tuple[str, int]],
                      reference: str, case_name: str, budget: int, truth_known: bool,
                      workers: int = 1, case=None):
    """``campaigns``: campaign name -> (method, seed). Writes ``calls.parquet`` (one row per
    call), ``runs.parquet`` (one per method x seed), ``summary.parquet``, ``summary.md`` and
    ``best_so_far.png`` as a version of ``<bench>/benchmark``. ``case`` (the loaded case):
    campaigns chosen by the likelihood are judged by it (:func:`objective_values`)."""
    store = ArtifactStore(store_root)
    ref = {r["index"]: r for r in EvaluationJournal(store, reference).rows()}
    for i, what in ((0, "floor (the truth's values or the deck's own)"), (1, "prior centre")):
        if i not in ref or ref[i].get("E") is None or not np.isfinite(ref[i]["E"]):
            raise ValueError(f"the {what} run of {reference} has no misfit "
                             f"({ref.get(i, {}).get('reason', 'not run')}): no benchmark "
                             "table without it; fix the case and rerun")
    floor, centre = float(ref[0]["E"]), float(ref[1]["E"])
    objective = objective_of(store, campaigns)
    frames, floors = [], {}
    for name, (method, seed) in campaigns.items():
        rows = [r for r in EvaluationJournal(store, name).rows() if r["index"] < budget]
        values, floors[(method, seed)] = objective_values(store, name, rows, objective,
                                                          (floor, centre), case, ref)
        frames.append(pd.DataFrame({
            "method": method, "seed": seed, "call": [r["index"] + 1 for r in rows],
            "status": [r["status"] for r in rows],
            "E": values,
            "E_paper": [np.nan if r.get("E") is None else r["E"] for r in rows],
            "penalty": [r.get("penalty") for r in rows],
            "phase": [r.get("phase") for r in rows],
            "wall_time_s": [r.get("wall_time_s") for r in rows],
            "sim_time_s": [r.get("sim_time_s") for r in rows],
            "finished_at": [r.get("finished_at", np.nan) for r in rows],
            "worst_well_cmatch": [worst_well_cmatch(r.get("metrics") or {}) for r in rows]}))
    calls = benchmark.best_so_far(pd.concat(frames, ignore_index=True))
    runs = pd.concat([benchmark.per_run(g, *floors[key], workers)
                      for key, g in calls.groupby(["method", "seed"], sort=False)],
                     ignore_index=True)
    table = benchmark.summary(runs)
    text = benchmark.markdown(table, floor, centre, case_name, truth_known)
    if objective == "likelihood":
        lows = [f for f, _ in floors.values()]
        text = (f"Objective: the likelihood (chi2/n). The columns named E hold it; each "
                f"campaign's floor is the truth's likelihood under the noise that campaign "
                f"ended with (median {np.nanmedian(lows):.6g}); the floor E below is the "
                "paper's E, for reference.\n\n" + text)
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / "best_so_far.png"
        benchmark.plot(calls, floor, png, f"{case_name}: best-so-far E vs simulator calls")
        files = {"calls.parquet": calls, "runs.parquet": runs, "summary.parquet": table,
                 "summary.md": text, "best_so_far.png": png.read_bytes(),
                 "references.json": {"objective": objective, "floor_E": floor,
                                     "centre_E": centre,
                                     "floors": {f"{m}-s{s}": v for (m, s), v in floors.items()},
                                      "floor_values": ref[0]["params"],
                                      "centre_values": ref[1]["params"]}}
        journals = {name: int(((calls.method == m) & (calls.seed == s)).sum())
                    for name, (m, s) in campaigns.items()}
        return store.put_files(bench, "benchmark", {"campaigns": campaigns, "calls": journals,
                                                    "reference": reference, "budget": budget},
                               files, code_version())


def objective_of(store: ArtifactStore, campaigns: dict[str, tuple[str, int]]) -> str:
    """The objective the benchmark's campaigns chose by (their case's; E for campaigns
    stored before the objective was)."""
    stored = [(store.settings(name) or {}).get("objective", "E") for name in campaigns]
    return stored[0] if stored else "E"


def final_objective(store: ArtifactStore, campaign: str, case, journal: dict[int, dict]
                    ) -> Objective:
    """The objective a campaign ended with, rebuilt from its journal: the case's, refined in
    turn from the call each of its stored noise refinements names (``noise/v*/noise.json``;
    the latest version of each refinement). A function of the journal and that chain only, so
    a benchmark unpacked on another machine (``export_bench.py`` carries both) scores alike."""
    objective = Objective.of_case(case)
    chain: dict[int, int] = {}
    for version in store.versions(campaign, NOISE_STEP):
        doc = version.read_json("noise.json")
        chain[int(doc["refinement"])] = int(doc["refined_from_call"])
    for k in sorted(chain):
        record = journal.get(chain[k])
        if record is None or not objective.refinable or objective.simulated(record) is None:
            break
        objective = objective.refined(record)
    return objective


def objective_values(store: ArtifactStore, campaign: str, rows: list[dict], objective: str,
                     references: tuple[float, float], case=None,
                     reference_records: dict[int, dict] | None = None
                     ) -> tuple[list[float], tuple[float, float]]:
    """Each call's value of ``objective`` and the (floor, centre) it is judged against: E and
    the benchmark's references, or the likelihood under the noise the campaign ended with
    (:func:`final_objective`) and the references scored by it."""
    if objective == "E" or case is None:
        return [np.nan if r.get("E") is None else r["E"] for r in rows], references
    final = final_objective(store, campaign, case, {r["index"]: r for r in rows})
    refs = reference_records or {}
    pair = tuple(final.likelihood(refs[i]) if i in refs else np.nan for i in (0, 1))
    return [final.likelihood(r) for r in rows], pair
