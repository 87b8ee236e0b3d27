"""Run one OPM Flow simulation through the ``opm-simulators`` Python bindings.

Executed as ``python -m hmcore.opm_runner DECK OUTPUT_DIR [extra flow options...]`` in a fresh
process for every run: the bindings write no output for a second run in the same process.
Exit codes: 0 finished, 2 deck could not be parsed, 3 simulator raised while stepping.
"""

from __future__ import annotations

import sys


def main(argv: list[str]) -> int:
    deck, output_dir, *extra = argv
    from opm.simulators import BlackOilSimulator

    args = [
        f"--output-dir={output_dir}",
        "--output-mode=none",
        "--enable-terminal-output=false",
        "--threads-per-process=1",
        *extra,
    ]
    sim = BlackOilSimulator(deck, args)
    if sim.step_init() != 0:
        print(f"hmflow: OPM could not initialise the deck {deck}", file=sys.stderr)
        return 2
    try:
        while not sim.check_simulation_finished():
            sim.step()
        sim.step_cleanup()
    except Exception as exc:  # the bindings raise plain RuntimeError on failed time steps
        print(f"hmflow: simulator stopped: {exc}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
