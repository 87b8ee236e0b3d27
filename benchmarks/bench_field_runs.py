"""What a field-size run costs, and what threads per run and a shorter history window save.

    python benchmarks/bench_field_runs.py --case spe9.toml [--stop-day 450] [--repeat 2]
        [--mpi-command "mpirun --allow-run-as-root -np {processes} flow {deck} ..."]

Runs the case's deck at its prior centre (the middle of every parameter range) with 1 and 2
threads per run, over the whole schedule and stopped at the report step of ``--stop-day``
(the ``stop_at_last_observation`` setting with the history cut there), one run at a time;
with ``--mpi-command``, also the whole schedule through that command backend on 1 and 2 MPI
processes per run (the same simulator both times, so the two compare); and prints a Markdown table of simulator wall times (median of ``--repeat``). Run it on a quiet
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
    from hmcore.cases import load_case
    from hmcore.scoring.evaluation import evaluate, simulator_for

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=Path, required=True)
    ap.add_argument("--stop-day", type=float, default=None,
                    help="also run with the history cut at this day (default: half the schedule)")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--mpi-command", default=None,
                    help="a command backend with {processes}, e.g. 'mpirun -np {processes} flow "
                         "{deck} --output-dir={run_dir} --enable-terminal-output=false'")
    args = ap.parse_args()
    base = load_case(args.case)
    stop_day = args.stop_day or base.info.end_days / 2
    cut = base.observed[base.observed.days <= stop_day]
    centre = dict(zip(base.space.names, (base.space.low + base.space.high) / 2))
    settings = [(f"{t} thread(s)", {"threads": t, "stop_at_last_observation": stopped})
                for t in (1, 2) for stopped in (False, True)]
    if args.mpi_command:
        settings += [(f"{n} MPI process(es), command backend",
                      {"backend": args.mpi_command, "processes": n}) for n in (1, 2)]
    rows = []
    for label, update in settings:
        stopped = update.get("stop_at_last_observation", False)
        window = f"stopped after day {stop_day:g}" if stopped else "whole schedule"
        case = replace(base, observed=cut if stopped else base.observed,
                       simulator=base.simulator.model_copy(update=update))
        times = []
        for _ in range(args.repeat):
            with tempfile.TemporaryDirectory(prefix="hmflow-field-") as tmp:
                ev = evaluate(case, centre, Path(tmp) / "run", simulator_for(case))
                if ev.status.value == "FAIL":
                    raise SystemExit(f"run failed: {ev.reason}")
                times.append(ev.sim_time_s)
        rows.append((label, window, case.run_end_days, statistics.median(times)))
        print(f"{label}, {window}: {statistics.median(times):.1f} s", flush=True)
    full = rows[0][3]
    print(f"\n{base.name}: {base.info.nactive} active cells, {len(base.info.wells)} wells, "
          f"{base.info.end_days:g} days; median of {args.repeat} runs\n")
    print("| per run | simulated | simulator wall time | vs 1 thread, whole |")
    print("|---|---|---|---|")
    for label, window, end, t in rows:
        print(f"| {label} | {window} (to day {end:g}) | {t:.1f} s | {full / t:.2f}x |")


if __name__ == "__main__":
    main()
