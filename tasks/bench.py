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
from storage import ArtifactStore, EvaluationJournal, code_version


@task(name="consolidate-benchmark", cache_policy=NO_CACHE)
def consolidate_bench(store_root: str, bench: str, campaigns: dict[str, tuple[str, int]],
                      reference: str, case_name: str, budget: int, truth_known: bool,
                      workers: int = 1):
    """``campaigns``: campaign name -> (method, seed). Writes ``calls.parquet`` (one row per
    call), ``runs.parquet`` (one per method x seed), ``summary.parquet``, ``summary.md`` and
    ``best_so_far.png`` as a version of ``<bench>/benchmark``."""
    store = ArtifactStore(store_root)
    ref = {r["index"]: r for r in EvaluationJournal(store, reference).rows()}
    for i, what in ((0, "floor (the truth's values or the deck's own)"), (1, "prior centre")):
        if i not in ref or ref[i].get("E") is None or not np.isfinite(ref[i]["E"]):
            raise ValueError(f"the {what} run of {reference} has no misfit "
                             f"({ref.get(i, {}).get('reason', 'not run')}): no benchmark "
                             "table without it; fix the case and rerun")
    floor, centre = float(ref[0]["E"]), float(ref[1]["E"])
    frames = []
    for name, (method, seed) in campaigns.items():
        rows = [r for r in EvaluationJournal(store, name).rows() if r["index"] < budget]
        frames.append(pd.DataFrame({
            "method": method, "seed": seed, "call": [r["index"] + 1 for r in rows],
            "status": [r["status"] for r in rows],
            "E": [np.nan if r.get("E") is None else r["E"] for r in rows],
            "penalty": [r.get("penalty") for r in rows],
            "phase": [r.get("phase") for r in rows],
            "wall_time_s": [r.get("wall_time_s") for r in rows],
            "sim_time_s": [r.get("sim_time_s") for r in rows],
            "finished_at": [r.get("finished_at", np.nan) for r in rows],
            "worst_well_cmatch": [worst_well_cmatch(r.get("metrics") or {}) for r in rows]}))
    calls = benchmark.best_so_far(pd.concat(frames, ignore_index=True))
    runs = benchmark.per_run(calls, floor, centre, workers)
    table = benchmark.summary(runs)
    text = benchmark.markdown(table, floor, centre, case_name, truth_known)
    with tempfile.TemporaryDirectory() as tmp:
        png = Path(tmp) / "best_so_far.png"
        benchmark.plot(calls, floor, png, f"{case_name}: best-so-far E vs simulator calls")
        files = {"calls.parquet": calls, "runs.parquet": runs, "summary.parquet": table,
                 "summary.md": text, "best_so_far.png": png.read_bytes(),
                 "references.json": {"floor_E": floor, "centre_E": centre,
                                      "floor_values": ref[0]["params"],
                                      "centre_values": ref[1]["params"]}}
        journals = {name: int(((calls.method == m) & (calls.seed == s)).sum())
                    for name, (m, s) in campaigns.items()}
        return store.put_files(bench, "benchmark", {"campaigns": campaigns, "calls": journals,
                                                    "reference": reference, "budget": budget},
                               files, code_version())
