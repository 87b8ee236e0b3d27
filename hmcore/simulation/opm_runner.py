"""Run one OPM Flow simulation through the ``opm-simulators`` Python bindings.

Executed as ``python -m hmcore.simulation.opm_runner DECK OUTPUT_DIR [extra flow options...]`` in a fresh
process for every run: the bindings write no output for a second run in the same process.
``--hmflow-stop-step=N`` (hmflow's own) ends the run after report step N.
Exit codes: 0 finished, 2 deck could not be parsed, 3 simulator raised while stepping.
"""

from __future__ import annotations

import sys

STOP = "--hmflow-stop-step="  # hmflow's own option: stop after this report step


def main(argv: list[str]) -> int:
    deck, output_dir, *extra = argv
    stop = next((int(a[len(STOP):]) for a in extra if a.startswith(STOP)), None)
    extra = [a for a in extra if not a.startswith(STOP)]
    from opm.simulators import BlackOilSimulator

    args = [
        f"--output-dir={output_dir}",
        "--output-mode=none",
        "--enable-terminal-output=false",
        *extra,
    ]
    if not any(a.startswith("--threads-per-process=") for a in extra):
        args.append("--threads-per-process=1")
    sim = BlackOilSimulator(deck, args)
    if sim.step_init() != 0:
        print(f"hmflow: OPM could not initialise the deck {deck}", file=sys.stderr)
        return 2
    try:
        while not sim.check_simulation_finished():
            if stop is not None and sim.current_step() >= stop:
                break  # the rest of the schedule is not needed (no observation after it)
            sim.step()
        sim.step_cleanup()
    except Exception as exc:  # the bindings raise plain RuntimeError on failed time steps
        print(f"hmflow: simulator stopped: {exc}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
