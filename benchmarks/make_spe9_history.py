"""SPE9 as an operator would hand it over for history matching: the measured rates in the
schedule as ``WCONHIST`` / ``WCONINJH`` records, with a truth that is not the deck's own.

    python benchmarks/make_spe9_history.py --out bench-cases/spe9-history [--seed 0]

1. The public SPE9 deck (``../shared/spe9/SPE9.DATA``, read in place, never copied into the
   repository) is run once with OPM Flow as the *truth*: permeability moved inside the default
   box (PERMX and PERMY x1.8, PERMZ x0.6) and one hidden effect the calibration's globals cannot
   express: a skin of 12 on the connections of PRODU12 (every other well keeps the deck's 0).
2. Its rates and pressures at every report step get measurement noise (AR(1) in time,
   ``numpy.random.default_rng(seed)``): 3 % on oil, water and gas rates and the injected rate,
   10 psi on bottom-hole pressures.
3. ``OUT/SPE9_HM.DATA`` is written: SPE9's own text up to its schedule, ``INCLUDE`` paths made
   absolute (to ``../shared``), then for every 10-day step a ``WCONHIST`` record per producer
   (control ORAT: oil, water, gas rate and BHP) and a ``WCONINJH`` record for INJE1 (control
   RATE: rate and BHP), ``TSTEP 10``. The truth is in ``OUT/truth.json``.

The deck then goes the way of any field's deck: ``hmflow init --deck OUT/SPE9_HM.DATA``.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SHARED_DECK = REPO.parent / "shared" / "spe9" / "SPE9.DATA"
TRUTH = {"permx_mult": 1.8, "permy_mult": 1.8, "permz_mult": 0.6, "skin_PRODU12": 12.0}
RATE_NOISE = 0.03   # relative
BHP_NOISE = 10.0    # psi
RHO = 0.7           # AR(1) coefficient between 10-day steps


def truth_space():
    from hmcore.model.parameters import Parameter, ParameterSpace

    return ParameterSpace(parameters=(
        Parameter(name="permx_mult", kind="multiply", keywords=("PERMX",), low=0.3, high=3.0),
        Parameter(name="permy_mult", kind="multiply", keywords=("PERMY",), low=0.3, high=3.0),
        Parameter(name="permz_mult", kind="multiply", keywords=("PERMZ",), low=0.3, high=3.0),
        Parameter(name="skin_PRODU12", kind="skin", wells=("PRODU12",), low=-5.0, high=20.0),
    ))


def run_truth(deck: Path, work: Path) -> tuple[pd.DataFrame, tuple[float, ...]]:
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.simulation.responses import read_responses
    from hmcore.simulation.simulator import OpmFlow

    info = DeckInfo.inspect(deck)
    run_deck = prepare_run_deck(deck, TRUTH, truth_space(), work, info)
    result = OpmFlow(timeout_s=1800).run(run_deck, work)
    return read_responses(result.summary_path, sorted(info.wells)), info.report_days


def measured(truth: pd.DataFrame, report_days: tuple[float, ...], seed: int) -> pd.DataFrame:
    """Wide table (well, days) -> noisy WOPR, WWPR, WGPR, WWIR, WBHP at the report days (the
    summary also holds the simulator's own time steps between them)."""
    from hmcore.ordering import natural_key
    from hmcore.scenarios.synthetic import ar1_series

    rng = np.random.default_rng(seed)
    at_report = np.isin(np.round(truth.days.to_numpy(float), 2), np.round(report_days[1:], 2))
    wide = truth[at_report].pivot_table(index=["well", "days"], columns="quantity",
                                             values="value")
    out = []
    for well in sorted(wide.index.get_level_values("well").unique(), key=natural_key):
        t = wide.loc[well].copy()
        for q in ("WOPR", "WWPR", "WGPR", "WWIR"):
            if q in t:
                t[q] = np.maximum(t[q].to_numpy() * (1 + RATE_NOISE * ar1_series(rng, len(t), RHO)), 0.0)
        t["WBHP"] = t["WBHP"].to_numpy() + BHP_NOISE * ar1_series(rng, len(t), RHO)
        out.append(t.assign(well=well).reset_index())
    return pd.concat(out, ignore_index=True)


def schedule_text(data: pd.DataFrame) -> str:
    lines = []
    for days, step in data.groupby("days", sort=True):
        lines.append(f"-- measured over the 10 days ending on day {days:g}\nWCONHIST\n")
        for _, r in step.iterrows():
            if r.well.startswith("PRODU"):
                lines.append(f"  '{r.well}' 'OPEN' 'ORAT' {r.WOPR:.6g} {r.WWPR:.6g} "
                             f"{r.WGPR:.6g} 1* 1* 1* {r.WBHP:.6g} /\n")
        lines.append("/\nWCONINJH\n")
        for _, r in step.iterrows():
            if r.well.startswith("INJE"):
                lines.append(f"  '{r.well}' 'WATER' 'OPEN' {r.WWIR:.6g} {r.WBHP:.6g} "
                             "6* 'RATE' /\n")
        lines.append("/\nTSTEP\n  10 /\n\n")
    return "".join(lines)


def history_deck(deck: Path, data: pd.DataFrame) -> str:
    text = deck.read_text()
    cut = text.index("WCONINJE")  # SPE9's own controls start here; the history replaces them
    head = text[:cut]
    head = re.sub(r"INCLUDE\s*\n\s*'?([A-Za-z0-9_.]+)'?\s*/",
                  lambda m: f"INCLUDE\n  '{(deck.parent / m.group(1)).resolve()}' /", head)
    return ("-- SPE9 as a history-matching deck, written by benchmarks/make_spe9_history.py\n"
            + head + schedule_text(data) + "END\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--deck", type=Path, default=SHARED_DECK)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    out = args.out
    target = out / "SPE9_HM.DATA"
    if target.exists():
        print(f"{target} exists: kept as it is")
        return
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="spe9-truth-") as tmp:
        truth, report_days = run_truth(args.deck.resolve(), Path(tmp) / "truth")
    truth.to_csv(out / "truth_responses.csv", index=False)
    data = measured(truth, report_days, args.seed)
    target.write_text(history_deck(args.deck.resolve(), data))
    (out / "truth.json").write_text(json.dumps(
        {"truth": TRUTH, "seed": args.seed, "hidden": {"kind": "skin", "wells": ["PRODU12"],
                                                        "value": TRUTH["skin_PRODU12"]},
         "noise": {"rate_relative": RATE_NOISE, "bhp_psi": BHP_NOISE, "ar1": RHO}},
        indent=2) + "\n")
    print(f"{target}: {data.days.nunique()} report steps, {data.well.nunique()} wells")


if __name__ == "__main__":
    main()
