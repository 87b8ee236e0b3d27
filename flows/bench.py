"""The benchmark flow: (for a ``[latent]`` case, the fields' prior modes, as a campaign makes
them) -> the reference runs (floor, prior centre) -> one ordinary campaign per
method x seed (each resumes after a kill; a stopped benchmark continues where it was) ->
consolidate into Parquet, a Markdown table and a plot."""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger

from flows.campaign import DEFAULT_STORAGE, campaign_flow, check_campaign_settings
from flows.labels import named_run
from flows.refuse import USER_ERRORS, input_problems, refused, scalar_problems
from flows.runners import Runner
from flows.runners import task_runner as make_runner
from hmcore.calibration.methods import AGENTS, method_version
from hmcore.cases import load_case
from hmcore.reporting.benchmark import case_truth
from hmcore.scoring.evaluation import SCORING_VERSION
from storage import ArtifactStore, EvaluationJournal
from tasks.bench import consolidate_bench
from tasks.case import prepare_deck
from tasks.latent import latent_conflict, latent_settings, prepare_latent, reference_runs
from tasks.reference import reference_settings, run_references
from tasks.simulate import observation_set


def bench_names(case_name: str, methods: list[str], seeds: list[int], name: str | None = None
                ) -> tuple[str, str, dict[str, tuple[str, int]]]:
    """(benchmark name, reference campaign, {campaign: (method, seed)}), seed by seed: a
    benchmark stopped part-way has every method on its first seeds."""
    bench = name or f"bench-{case_name}"

    def campaign(m: str, s: int) -> str:  # a method's later version is another campaign
        v = method_version(m)
        return f"{bench}-{m}-s{s}" if v == 1 else f"{bench}-{m}-v{v}-s{s}"

    return bench, f"{bench}-reference", {campaign(m, s): (m, s) for s in seeds for m in methods}


def same_settings(store_root: str | Path, campaign: str, method: str, seed: int,
                  workers: int, objective: str = "E") -> bool | None:
    """Whether a campaign of this benchmark was stored under this method, seed, workers,
    scoring rules and objective (None: no settings stored yet, the campaign has not
    started)."""
    stored = ArtifactStore(store_root).settings(campaign)
    if stored is None:
        return None
    return (stored.get("agent"), stored.get("seed"), stored.get("workers"),
            stored.get("scoring_version"), stored.get("method_version", 1),
            stored.get("objective", "E")) == (
        method, seed, workers, SCORING_VERSION, method_version(method), objective)


def same_bench(store_root: str | Path, bench: str, budget: int, workers: int) -> bool | None:
    """Whether the benchmark itself was stored with this budget and worker count (None: not
    started). Another budget or worker count is another benchmark, refused by the flow."""
    stored = ArtifactStore(store_root).settings(bench)
    if stored is None:
        return None
    # a key not stored yet (older stores): not checked
    return all(stored[k] == v for k, v in (("budget", budget), ("workers", workers))
               if k in stored)


def complete(store: ArtifactStore, campaign: str, method: str, seed: int, budget: int,
             workers: int, objective: str = "E") -> bool:
    """A campaign of this benchmark with all its calls journaled, under the same method, seed,
    workers and scoring rules: nothing to run (its journal is read as it is). Anything else
    goes through the campaign flow, which resumes it or refuses other settings."""
    return (same_settings(store.root, campaign, method, seed, workers, objective) is True
            and len(EvaluationJournal(store, campaign).indices()) >= budget)


@flow(name="hmflow-bench", log_prints=True, flow_run_name=named_run("name", "bench"))
def bench_flow(case: str = "synthetic", methods: list[str] | None = None,
               seeds: list[int] | None = None, budget: int = 100, workers: int = 2,
               storage: str = DEFAULT_STORAGE, name: str | None = None,
               task_runner: Runner = "threads", dask_address: str | None = None) -> dict:
    """Every method x seed at the same ``budget`` of simulator calls on ``case`` (the
    simulator calls on ``task_runner``, as in the campaign flow)."""
    logger = get_run_logger()
    storage = str(Path(storage).expanduser().resolve())
    methods = list(methods or AGENTS)
    seeds = list(seeds if seeds is not None else range(5))
    try:  # bad input from the UI or the API: one clear line, no traceback, no simulation
        problems = list(dict.fromkeys(p for m in methods
                                      for p in input_problems(m, budget, workers, task_runner)))
        if problems:
            raise ValueError("; ".join(problems))
        loaded = load_case(case)
        problems = scalar_problems(loaded, latent=True)
        if problems:
            raise ValueError("; ".join(problems))
    except USER_ERRORS as exc:
        return refused(exc)
    bench, reference, campaigns = bench_names(loaded.name, methods, seeds, name)
    conflict = latent_conflict(storage, reference, loaded)  # before anything is written
    if conflict:
        return refused(ValueError(conflict))
    latent = prepare_latent(loaded, storage, reference) if loaded.latent else None
    loaded = latent.case if latent is not None else loaded  # the fields' modes, first
    case_version = prepare_deck(loaded, case, storage, reference)
    check_campaign_settings(storage, reference, {**reference_settings(case_version),
                                                 **latent_settings(loaded, latent)})
    # one benchmark, one budget: methods compared at another budget or worker count are
    # another benchmark (another --name)
    check_campaign_settings(storage, bench, {"case_artifact": case_version.ref(),
                                             "budget": budget, "workers": workers})
    with make_runner(task_runner, workers, dask_address, loaded.cluster) as started:
        run_references(loaded, storage, reference, started, observation_set(loaded),
                       **reference_runs(latent))
    store = ArtifactStore(storage)
    for campaign, (method, seed) in campaigns.items():
        if complete(store, campaign, method, seed, budget, workers, loaded.misfit.objective):
            logger.info(f"benchmark {bench}: {method} seed {seed} complete ({campaign})")
            continue
        logger.info(f"benchmark {bench}: {method} seed {seed} ({campaign})")
        campaign_flow(case=case, agent=method, budget=budget, workers=workers, seed=seed,
                      storage=storage, campaign=campaign, reference=reference,
                      task_runner=task_runner, dask_address=dask_address,
                      forecast_draws=0)  # equal budgets and wall times: no draws after
    version = consolidate_bench(storage, bench, campaigns, reference, loaded.name, budget,
                                case_truth(loaded.source) is not None, workers, loaded)
    return {"benchmark": bench, "storage": storage, "artifact": version.ref(),
            "summary_path": str(version.file("summary.md")),
            "plot_path": str(version.file("best_so_far.png"))}
