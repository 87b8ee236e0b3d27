"""Hidden-effect sweep of the diagnosis: hit rate per kind, gain, simulator calls and wall time.

    python benchmarks/bench_diagnosis.py --case synthetic --kinds all --seeds 11 12 \\
        --controls 6 7 [--workers 2] [--json out.json]
    python benchmarks/bench_diagnosis.py --case punq --kinds all --seeds 21
    python benchmarks/bench_diagnosis.py --case punq --record-end 0 --history-end 0  # as `hide`
    python benchmarks/bench_diagnosis.py --case punq-real        # PUNQ-S3's measured history

For each (kind, seed) a case is written whose truth hides one extension drawn by the seed
(:mod:`hmcore.diagnosis.hidden`): the synthetic case (seeded fields and noise, the known
five-parameter truth) or PUNQ-S3 (truth run of PUNQS3.DATA with the effect applied, PUNQ-style
AR(1) noise, no sigma in the CSV, record to day 2936, fitted to day 2200; ``--record-end 0
--history-end 0``: `hmflow hide`'s defaults, the whole schedule, 75 % of it fitted). The diagnosis runs on
the base model, ``workers`` simulations at a time, and is judged by
:func:`hmcore.diagnosis.hidden.judge`: right kind (and well / layer / plane) ranked first,
selected, held-back misfit improved. Controls hide nothing and must report ``none``.
Nothing is asserted; the table and the JSON go into the notes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PUNQ = Path(__file__).resolve().parents[2] / "shared" / "punqs3"
PUNQ_TRUTH = {"poro_mult": 1.0, "permx_mult": 1.0, "permy_mult": 1.0, "permz_mult": 1.0,
              "skin": 5.0}


def one(case: str, kind: str | None, seed: int, root: Path, workers: int,
        history_end: float = 2200.0, record_end: float = 2936.0) -> dict:
    from hmcore.case import load_case
    from hmcore.diagnosis import diagnose, local_evaluator
    from hmcore.diagnosis.hidden import (judge, write_hidden_deck_case,
                                         write_hidden_synthetic_case)

    tmp = root / f"{case}-{kind or 'control'}-{seed}"
    t0 = time.perf_counter()
    if case == "synthetic":
        toml, effect = write_hidden_synthetic_case(tmp / "case", seed, kind)
    elif case == "punq":
        toml, effect = write_hidden_deck_case(tmp / "case", PUNQ / "PUNQS3.DATA", seed,
                                              truth=PUNQ_TRUTH, kind=kind,
                                              history_end_days=history_end or None,
                                              with_sigma=False, end_days=record_end or None,
                                              name="punq-hidden")
    else:
        tmp.mkdir(parents=True, exist_ok=True)
        toml = tmp / "case.toml"
        toml.write_text(f'[case]\nname = "punqs3"\ndeck = "{PUNQ / "PUNQS3.DATA"}"\n'
                        f'observed = "{PUNQ / "punqs3_observed_full_history.csv"}"\n'
                        "history_end_days = 2200\n")
        effect = None
    doc = diagnose(load_case(toml), local_evaluator(tmp / "runs", workers), out_dir=tmp / "out")
    wall = time.perf_counter() - t0
    shutil.rmtree(tmp / "runs", ignore_errors=True)
    signal = (json.loads((tmp / "case" / "hidden_effect.json").read_text()).get("signal")
              if case != "punq-real" else None) or {}
    out = judge(doc, effect, signal) if case != "punq-real" else {
        "ranking": [f"{c['id']} ({c['chi2']:.0f})" for c in doc["causes"][:5]
                    if c["chi2"] is not None], "verdict": doc["verdict"], "gain": doc["gain"]}
    out.update({"signal_fit": signal.get("chi2_fit"), "signal_heldout": signal.get("chi2_heldout"),
                "signal_fit_after_globals": signal.get("chi2_fit_after_globals"),
                "visible": signal.get("visible_in_fitted_history")})
    out.update({"case": case, "kind": kind or "control", "seed": seed, "wall_s": wall,
                "simulations": doc["cost"]["simulations"], "out": str(tmp / "out"),
                "selected": out.get("selected", doc["selected"] and doc["selected"]["id"])})
    return out


def main() -> None:
    from hmcore.diagnosis.extensions import KINDS

    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=("synthetic", "punq", "punq-real"), default="synthetic")
    ap.add_argument("--kinds", nargs="+", default=["all"])
    ap.add_argument("--seeds", nargs="*", type=int, default=[11, 12])
    ap.add_argument("--controls", nargs="*", type=int, default=[])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--root", type=Path)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--history-end", type=float, default=2200.0,
                    help="punq: days fitted (0: 75 %% of the record, as `hmflow hide`)")
    ap.add_argument("--record-end", type=float, default=2936.0,
                    help="punq: last day of the measured record (0: the schedule's end)")
    args = ap.parse_args()
    kinds = list(KINDS) if args.kinds == ["all"] else args.kinds
    root = args.root or Path(tempfile.mkdtemp(prefix="hmflow-bench-diagnosis-"))
    jobs = ([(None, 0)] if args.case == "punq-real" else
            [(k, s) for k in kinds for s in args.seeds] + [(None, s) for s in args.controls])
    rows = []
    for kind, seed in jobs:
        try:
            row = one(args.case, kind, seed, root, args.workers, args.history_end,
                      args.record_end)
        except Exception as exc:  # report and go on: a sweep is a measurement
            row = {"case": args.case, "kind": kind or "control", "seed": seed,
                   "error": f"{type(exc).__name__}: {exc}", "found": False}
        rows.append(row)
        print(json.dumps({k: row.get(k) for k in ("case", "kind", "seed", "hidden", "found",
                                                   "ranked_first", "selected", "signal_fit",
                                                   "signal_heldout", "signal_fit_after_globals",
                                                   "visible", "wall_s",
                                                   "simulations", "ranking", "error")}),
              flush=True)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=2, default=str))
    if args.case != "punq-real":
        print("\nkind | cases | visible in the fitted history (after the globals absorb) | "
              "ranked first | found (first + selected + held-back better) | mean wall s | "
              "mean simulations")
        for kind in kinds + (["control"] if args.controls else []):
            sub = [r for r in rows if r["kind"] == kind]
            if sub:
                n = len(sub)
                first = sum(bool(r.get("ranked_first")) for r in sub)
                found = sum(bool(r.get("found")) for r in sub)
                wall = sum(r.get("wall_s", 0) for r in sub) / n
                sims = sum(r.get("simulations", 0) for r in sub) / n
                seen = sum(bool(r.get("visible")) for r in sub)
                print(f"{kind} | {n} | {seen}/{n} | {first}/{n} | {found}/{n} | {wall:.0f} | "
                      f"{sims:.0f}")
    print(f"\noutputs under {root}")


if __name__ == "__main__":
    main()
