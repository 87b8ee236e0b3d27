"""Campaign wall time with 1 and 2 workers, and what Prefect + Python add to the simulator time.

    python benchmarks/bench_campaign.py --case synthetic --budget 12 [--json out.json]

For each worker count a fresh campaign (random agent, same seed) runs through the real Prefect
flow on the thread-pool task runner. Reported per run: flow wall time, the sum of the
simulator subprocesses' own time (sim_time_s of every call, as recorded), the speed-up of
2 workers over 1, and the overhead ``(wall * workers - sum sim) / sum sim`` with 1 worker,
i.e. everything that is not the simulator: Prefect task orchestration, deck preparation,
reading and scoring responses, the proposer, storage. The ephemeral Prefect server's start-up
is excluded by running a warm-up flow first (it is a one-off cost per process, ~5 s). Both
campaigns share one reference campaign, whose two simulations (truth and prior centre, outside
the budget) run in the warm-up, so the timed flows hold only the budgeted calls, the
consolidation, the curves and the report (report.html and its figures included).
Nothing here is asserted; the figures go into the notes and docs.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="synthetic")
    ap.add_argument("--budget", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    from prefect import flow

    from flows.campaign import campaign_flow
    from storage import ArtifactStore

    @flow
    def warm_up() -> int:
        return 1

    warm_up()
    root = Path(tempfile.mkdtemp(prefix="hmflow-bench-"))
    campaign_flow(case=args.case, agent="random", budget=1, workers=1, seed=args.seed,
                  storage=str(root), campaign="bench-warm-up", reference="bench-reference")
    out = {"case": args.case, "budget": args.budget, "runs": {}}
    for workers in (1, 2):
        name = f"bench-w{workers}"
        t0 = time.perf_counter()
        campaign_flow(
            case=args.case, agent="random", budget=args.budget, workers=workers, seed=args.seed,
            storage=str(root), campaign=name, reference="bench-reference")
        wall = time.perf_counter() - t0
        table = ArtifactStore(root).latest(name, "results").read_parquet("evaluations.parquet")
        sim = float(table["sim_time_s"].sum())
        evals = float(table["wall_time_s"].sum())
        out["runs"][workers] = {"wall_s": wall, "sum_sim_s": sim, "sum_eval_s": evals,
                                "calls": len(table), "mean_sim_s": sim / len(table),
                                "statuses": table["status"].value_counts().to_dict()}
        print(f"workers={workers}: wall {wall:.1f} s, {len(table)} calls, simulator {sim:.1f} s "
              f"(mean {sim / len(table):.2f} s), evaluate() {evals:.1f} s", flush=True)
    w1, w2 = out["runs"][1], out["runs"][2]
    out["speedup_ratio_w2_over_w1"] = w2["wall_s"] / w1["wall_s"]
    out["overhead_pct_w1"] = 100 * (w1["wall_s"] - w1["sum_sim_s"]) / w1["sum_sim_s"]
    out["overhead_pct_w1_outside_evaluate"] = 100 * (w1["wall_s"] - w1["sum_eval_s"]) / w1["sum_sim_s"]
    print(f"2-worker wall / 1-worker wall = {out['speedup_ratio_w2_over_w1']:.3f} (target < 0.6)")
    print(f"overhead with 1 worker (everything but the simulator) = {out['overhead_pct_w1']:.2f} % "
          f"of simulator time (target < 5 %); Prefect/flow part alone = "
          f"{out['overhead_pct_w1_outside_evaluate']:.2f} %")
    print(f"storage left in {root}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
