"""What a field-size run costs, and what threads per run and a shorter history window save.

    python benchmarks/bench_field_runs.py --case spe9.toml [--stop-day 450] [--repeat 2]

Runs the case's deck at its prior centre (the middle of every parameter range) with 1 and 2
threads per run, over the whole schedule and stopped at the report step of ``--stop-day``
(the ``stop_at_last_observation`` setting with the history cut there), one run at a time,
and prints a Markdown table of simulator wall times (median of ``--repeat``). Run it on a quiet
machine: the figures are wall-clock times.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    from hmcore.case import load_case
    from hmcore.evaluation import evaluate, simulator_for

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=Path, required=True)
    ap.add_argument("--stop-day", type=float, default=None,
                    help="also run with the history cut at this day (default: half the schedule)")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    base = load_case(args.case)
    stop_day = args.stop_day or base.info.end_days / 2
    cut = base.observed[base.observed.days <= stop_day]
    centre = dict(zip(base.space.names, (base.space.low + base.space.high) / 2))
    rows = []
    for threads in (1, 2):
        for window in ("whole schedule", f"stopped after day {stop_day:g}"):
            stopped = window != "whole schedule"
            case = replace(base, observed=cut if stopped else base.observed,
                           simulator=base.simulator.model_copy(update={
                               "threads": threads, "stop_at_last_observation": stopped}))
            times = []
            for r in range(args.repeat):
                with tempfile.TemporaryDirectory(prefix="hmflow-field-") as tmp:
                    ev = evaluate(case, centre, Path(tmp) / "run", simulator_for(case))
                    if ev.status.value == "FAIL":
                        raise SystemExit(f"run failed: {ev.reason}")
                    times.append(ev.sim_time_s)
            rows.append((threads, window, case.run_end_days, statistics.median(times)))
            print(f"threads {threads}, {window}: {statistics.median(times):.1f} s", flush=True)
    full = rows[0][3]
    print(f"\n{base.name}: {base.info.nactive} active cells, {len(base.info.wells)} wells, "
          f"{base.info.end_days:g} days; median of {args.repeat} runs\n")
    print("| threads per run | simulated | simulator wall time | vs 1 thread, whole |")
    print("|---|---|---|---|")
    for threads, window, end, t in rows:
        print(f"| {threads} | {window} (to day {end:g}) | {t:.1f} s | {full / t:.2f}x |")


if __name__ == "__main__":
    main()
