"""Per-evaluation overhead of hmflow outside the simulator (one evaluation at a time).

    python benchmarks/bench_evaluation.py [--case CASE.toml] [--runs 5] [--json out.json]

Without ``--case`` the PUNQ-S3 acceptance case (../shared/punqs3, full measured history,
history_end_days = 2936) is written to a temporary directory and used.

For every run, ``hmcore.scoring.evaluation.evaluate`` is timed as it reports itself:
``overhead = Evaluation.wall_time_s - Evaluation.sim_time_s``, i.e. everything that is not the
simulator subprocess (physics check, deck preparation, reading the summary twice - end time
and responses - alignment, misfit and metrics). ``sim_time_s`` is the wall time of the
simulator subprocess (for the default backend: a fresh Python that imports opm and runs Flow).
The three main parts are also timed on their own with ``time.perf_counter`` around
``hmcore.model.run_deck.prepare_run_deck`` (into a scratch dir), ``hmcore.simulation.responses.read_responses``
and ``hmcore.scoring.evaluation.score_responses`` on the run's summary. The overhead is reported as a
percentage of the simulator time; the target is < 3 %. Runs are sequential (never more than
one simulation at a time), so the simulator time is not inflated by this script.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
PUNQ_DIR = REPO.parent / "shared" / "punqs3"
TARGET_PCT = 3.0


def write_punq_case(directory: Path) -> Path:
    deck = PUNQ_DIR / "PUNQS3.DATA"
    observed = PUNQ_DIR / "punqs3_observed_full_history.csv"
    missing = [str(p) for p in (deck, observed) if not p.is_file()]
    if missing:
        sys.exit(f"PUNQ-S3 data not found ({missing}); give --case")
    path = directory / "punqs3.toml"
    path.write_text(f'[case]\nname = "punqs3"\ndeck = "{deck}"\nobserved = "{observed}"\n'
                    f"history_end_days = 2936\n")
    return path


def parse_values(sets: list[str], space) -> dict[str, float]:
    if sets:
        values = {}
        for item in sets:
            name, _, val = item.partition("=")
            if name not in space.names:
                sys.exit(f"--set {item!r}: unknown parameter; known: {space.names}")
            values[name] = float(val)
        return values
    truth = {"poro_mult": 1.0, "permx_mult": 1.0, "permy_mult": 1.0, "permz_mult": 1.0,
             "skin": 5.0}
    if set(space.names) == set(truth):  # the reference space: PUNQ-S3 truth values
        return truth
    return space.to_values([0.0] * space.dim)  # centre of the box


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", type=Path, default=None,
                    help="case TOML (default: the PUNQ-S3 case, written to a temp dir)")
    ap.add_argument("--runs", type=int, default=5, help="number of evaluations (default 5)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="NAME=VALUE",
                    help="parameter values (default: PUNQ-S3 truth / centre of the box)")
    ap.add_argument("--json", type=Path, default=None, help="write the results as JSON here")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="where run directories go (default: a new temp dir, removed at the end)")
    ap.add_argument("--keep", action="store_true", help="keep the temp dir with the runs")
    args = ap.parse_args(argv)

    from hmcore.cases import load_case
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.scoring.evaluation import evaluate, score_responses, simulator_for
    from hmcore.simulation.responses import read_responses

    work = args.workdir or Path(tempfile.mkdtemp(prefix="hmflow-bench-eval-"))
    work.mkdir(parents=True, exist_ok=True)
    case_path = args.case or write_punq_case(work)
    t = time.perf_counter()
    case = load_case(case_path)
    load_s = time.perf_counter() - t
    values = parse_values(args.sets, case.space)
    sim = simulator_for(case)
    wells = sorted(case.info.wells)

    rows = []
    for i in range(args.runs):
        run_dir = work / f"eval{i:03d}"
        ev = evaluate(case, values, run_dir, sim)
        row = {"run": i, "status": ev.status.value, "E": ev.E, "wall_s": ev.wall_time_s,
               "sim_s": ev.sim_time_s, "overhead_s": ev.wall_time_s - ev.sim_time_s}
        row["overhead_pct"] = 100.0 * row["overhead_s"] / ev.sim_time_s if ev.sim_time_s else None
        # the parts on their own
        t = time.perf_counter()
        prepare_run_deck(case.deck, values, case.space, work / f"prepare{i:03d}", case.info)
        row["prepare_s"] = time.perf_counter() - t
        summary = run_dir / f"{case.info.path.stem.upper()}.SMSPEC"
        if ev.status.value != "FAIL" and summary.is_file():
            t = time.perf_counter()
            responses = read_responses(summary, wells)
            row["read_s"] = time.perf_counter() - t
            t = time.perf_counter()
            score_responses(case, responses)
            row["score_s"] = time.perf_counter() - t
        else:
            row["read_s"] = row["score_s"] = None
            row["reason"] = ev.reason
        rows.append(row)
        print(f"run {i}: {row['status']} E={row['E']:.6g} wall {row['wall_s']:.3f} s "
              f"sim {row['sim_s']:.3f} s overhead {1000 * row['overhead_s']:.1f} ms", flush=True)

    ok = [r for r in rows if r["status"] != "FAIL"]
    if not ok:
        sys.exit("every evaluation failed: " + "; ".join(r.get("reason", "") for r in rows))

    def med(key: str) -> float:
        return statistics.median(r[key] for r in ok)

    total_sim = sum(r["sim_s"] for r in ok)
    total_over = sum(r["overhead_s"] for r in ok)
    summary = {
        "case": str(case_path), "case_name": case.name, "runs": args.runs, "completed": len(ok),
        "values": values, "backend": sim.name, "case_load_s": load_s,
        "median": {k: med(k) for k in ("wall_s", "sim_s", "overhead_s", "prepare_s", "read_s",
                                       "score_s")},
        "overhead_pct_of_sim": 100.0 * total_over / total_sim,
        "max_overhead_pct": max(r["overhead_pct"] for r in ok),
        "target_pct": TARGET_PCT,
    }
    summary["median"]["other_s"] = (summary["median"]["overhead_s"] - summary["median"]["prepare_s"]
                                    - summary["median"]["read_s"] - summary["median"]["score_s"])
    summary["meets_target"] = summary["overhead_pct_of_sim"] < TARGET_PCT
    result = {"summary": summary, "rows": rows}

    print()
    head = f"{'run':>3} {'status':<9} {'wall s':>8} {'sim s':>8} {'overhead ms':>11} {'%':>6} " \
           f"{'prepare ms':>10} {'read ms':>8} {'score ms':>8}"
    print(head)
    print("-" * len(head))
    fmt = lambda v: "n/a" if v is None else f"{1000 * v:.1f}"  # noqa: E731
    for r in rows:
        pct = "n/a" if r["overhead_pct"] is None else f"{r['overhead_pct']:.2f}"
        print(f"{r['run']:>3} {r['status']:<9} {r['wall_s']:>8.3f} {r['sim_s']:>8.3f} "
              f"{1000 * r['overhead_s']:>11.1f} {pct:>6} {fmt(r['prepare_s']):>10} "
              f"{fmt(r['read_s']):>8} {fmt(r['score_s']):>8}")
    m = summary["median"]
    print("-" * len(head))
    print(f"median: wall {m['wall_s']:.3f} s, simulator {m['sim_s']:.3f} s, overhead "
          f"{1000 * m['overhead_s']:.1f} ms (deck {1000 * m['prepare_s']:.1f} ms, read "
          f"{1000 * m['read_s']:.1f} ms, score {1000 * m['score_s']:.1f} ms, other "
          f"{1000 * m['other_s']:.1f} ms)")
    print(f"overhead = {summary['overhead_pct_of_sim']:.2f} % of simulator time (max per run "
          f"{summary['max_overhead_pct']:.2f} %); target < {TARGET_PCT} %: "
          f"{'met' if summary['meets_target'] else 'NOT met'}")
    print(f"case load (once, not per evaluation): {load_s:.3f} s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2, default=str))
        print(f"wrote {args.json}")
    if args.workdir is None and not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    else:
        print(f"runs kept in {work}")
    return result


if __name__ == "__main__":
    main()
