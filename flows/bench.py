"""The benchmark flow: the reference runs (floor, prior centre) -> one ordinary campaign per
method x seed (each resumes after a kill; a stopped benchmark continues where it was) ->
consolidate into Parquet, a Markdown table and a plot."""

from __future__ import annotations

import json
from pathlib import Path

from prefect import flow, get_run_logger
from prefect.task_runners import ThreadPoolTaskRunner

from flows.campaign import DEFAULT_STORAGE, campaign_flow, check_campaign_settings
from flows.labels import named_run
from storage import ArtifactStore, EvaluationJournal
from hmcore.benchmark import case_truth
from hmcore.evaluation import SCORING_VERSION
from tasks.bench import REFERENCE_AGENT, consolidate_bench, reference_jobs
from tasks.case import prepare_deck, validate_case
from tasks.simulate import simulate


def bench_names(case_name: str, methods: list[str], seeds: list[int], name: str | None = None
                ) -> tuple[str, str, dict[str, tuple[str, int]]]:
    """(benchmark name, reference campaign, {campaign: (method, seed)}), seed by seed: a
    benchmark stopped part-way has every method on its first seeds."""
    bench = name or f"bench-{case_name}"
    return bench, f"{bench}-reference", {f"{bench}-{m}-s{s}": (m, s) for s in seeds
                                          for m in methods}


def complete(store: ArtifactStore, campaign: str, method: str, seed: int, budget: int,
             workers: int) -> bool:
    """A campaign of this benchmark with all its calls journaled, under the same method, seed,
    workers and scoring rules: nothing to run (its journal is read as it is). Anything else
    goes through the campaign flow, which resumes it or refuses other settings."""
    path = store.root / campaign / "campaign.json"
    if not path.is_file() or len(EvaluationJournal(store, campaign).indices()) < budget:
        return False
    stored = json.loads(path.read_text())
    return (stored.get("agent"), stored.get("seed"), stored.get("workers"),
            stored.get("scoring_version")) == (method, seed, workers, SCORING_VERSION)


@flow(name="hmflow-bench", log_prints=True, flow_run_name=named_run("name", "bench"))
def bench_flow(case: str = "synthetic", methods: list[str] | None = None,
               seeds: list[int] | None = None, budget: int = 100, workers: int = 2,
               storage: str = DEFAULT_STORAGE, name: str | None = None) -> dict:
    """Every method x seed at the same ``budget`` of simulator calls on ``case``."""
    from hmcore.agents import AGENTS

    logger = get_run_logger()
    storage = str(Path(storage).resolve())
    methods = list(methods or AGENTS)
    seeds = list(seeds if seeds is not None else range(5))
    loaded = validate_case(case)
    bench, reference, campaigns = bench_names(loaded.name, methods, seeds, name)
    case_version = prepare_deck(loaded, case, storage, reference)
    check_campaign_settings(storage, reference, {"case_artifact": case_version.ref(),
                                                 "agent": REFERENCE_AGENT, "seed": 0,
                                                 "agent_settings": {},
                                                 "scoring_version": SCORING_VERSION})
    # one benchmark, one budget: methods compared at another budget or worker count are
    # another benchmark (another --name)
    check_campaign_settings(storage, bench, {"case_artifact": case_version.ref(),
                                             "budget": budget, "workers": workers})
    journal = EvaluationJournal(ArtifactStore(storage), reference)
    done = {r["index"] for r in journal.rows()}
    futures = [simulate.submit(loaded, job, storage, reference, 0, REFERENCE_AGENT)
               for job in reference_jobs(loaded) if job.index not in done]
    for f in futures:
        f.result()
    runner = campaign_flow.with_options(task_runner=ThreadPoolTaskRunner(max_workers=workers))
    store = ArtifactStore(storage)
    for campaign, (method, seed) in campaigns.items():
        if complete(store, campaign, method, seed, budget, workers):
            logger.info(f"benchmark {bench}: {method} seed {seed} complete ({campaign})")
            continue
        logger.info(f"benchmark {bench}: {method} seed {seed} ({campaign})")
        runner(case=case, agent=method, budget=budget, workers=workers, seed=seed,
               storage=storage, campaign=campaign)
    version = consolidate_bench(storage, bench, campaigns, reference, loaded.name, budget,
                                case_truth(loaded.source) is not None)
    return {"benchmark": bench, "storage": storage, "artifact": version.ref(),
            "summary_path": str(version.file("summary.md")),
            "plot_path": str(version.file("best_so_far.png"))}
