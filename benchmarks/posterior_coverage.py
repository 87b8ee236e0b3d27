"""Does the truth lie inside what a campaign reports about it? The identifiability's 95 %
intervals and the forecast's P90-P10 band from the posterior draws, on synthetic cases whose
truth is drawn inside the box (issue 44's measurement).

    python benchmarks/posterior_coverage.py --out bench-coverage [--seeds 1 2 ... 10]
        [--budget 60] [--draws 20] [--workers 2] [--results FILE]
    python benchmarks/posterior_coverage.py --out bench-coverage --table    # the table only

* **Cases**: the built-in synthetic case's generator (``write_synthetic_case``) with seed S
  (its prior fields and its noise) and the five globals of the truth drawn uniformly in the
  box until no physics check fires (``default_rng([S, 23])``); one OPM Flow run each, written
  once to ``OUT/synthetic-hidden-S/``.
* **Campaigns**: ``hmflow run --agent lm --budget B --forecast-draws D --seed 0`` in
  ``OUT/store``, run every time (a finished one resumes with no call; a stopped one where it
  stopped).
* **Figures**, per case, from the campaign's stored report and curves: how many of the five
  95 % intervals hold the truth, the pairs the report names, the forecast's kind and members,
  and for field cumulative oil (and water and gas) at the schedule's end: P90, P50, P10, the
  truth, whether it is inside, and the band's width (P10 - P90) / P50. Written after each case
  to ``--results`` (default ``benchmarks/results/posterior-coverage/results.json``).

Issue 44 asks the truth inside the intervals in at least 8 of 10 cases, and its field
cumulative oil inside P90-P10 in 6 to 10 of them (about 8 is calibrated).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from make_bench_cases import draw_valid_truth  # noqa: E402

from hmcore.scenarios.synthetic import write_synthetic_case  # noqa: E402
from storage import ArtifactStore  # noqa: E402

RESULTS = REPO / "benchmarks/results/posterior-coverage/results.json"
QUANTITIES = ("FOPT", "FWPT", "FGPT")


def make_case(out: Path, seed: int) -> Path:
    """``OUT/synthetic-hidden-S/case.toml``, written once: the seed's case with its prior
    truth first (for the deck), then again with the drawn truth."""
    folder = out / f"synthetic-hidden-{seed}"
    case = folder / "case.toml"
    if case.is_file():
        return case
    probe = out / f".probe-{seed}"
    write_synthetic_case(probe, seed)  # the seed's deck, to draw a truth its checks pass
    truth = draw_valid_truth(seed, probe / "SYNTH.DATA", stream=23)
    case = write_synthetic_case(folder, seed, truth=truth)
    shutil.rmtree(probe)
    return case


def figures(store: ArtifactStore, name: str) -> dict | None:
    """The case's figures from its stored report and curves (None: not finished)."""
    report = store.latest(name, "report")
    curves = store.latest(name, "curves")
    if report is None or curves is None:
        return None
    doc = json.loads(report.file("report.json").read_text())
    ident = doc.get("identifiability") or {}
    params = ident.get("parameters") or []
    forecast = curves.read_parquet("forecast.parquet")
    fdoc = curves.read_json("forecast.json")
    row = {"best_call": (doc.get("best") or {}).get("index", -1) + 1,
           "intervals_computed": bool(ident.get("computed")),
           "truth_inside_intervals": sum(bool(p.get("truth_inside")) for p in params),
           "intervals": len(params),
           "pairs": [f"{p['a']}~{p['b']} ({p['correlation']:+.2f})"
                     for p in ident.get("pairs") or []],
           "forecast_kind": fdoc.get("kind"),
           "members": int(forecast.members.max()) if len(forecast) else 0,
           "inflation": (fdoc.get("posterior") or {}).get("inflation")}
    for q in QUANTITIES:
        sel = forecast[(forecast.well == "FIELD") & (forecast.quantity == q)]
        if len(sel):
            r = sel.iloc[0]
            row[q] = {"P90": float(r.P90), "P50": float(r.P50), "P10": float(r.P10),
                      "truth": None if pd.isna(r.truth) else float(r.truth),
                      "inside": None if pd.isna(r.truth_inside) else bool(r.truth_inside),
                      "width": float((r.P10 - r.P90) / r.P50) if r.P50 else None}
    return row


def table(results: dict) -> str:
    lines = ["| case | best call | truth in 95 % intervals | pairs named | forecast | FOPT "
             "P90 / P50 / P10 (truth) | inside | width | FWPT inside | FGPT inside |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in sorted(results.items(), key=lambda kv: int(kv[0].rsplit("-", 1)[-1])):
        f = r.get("FOPT") or {}
        lines.append(
            f"| {name} | {r['best_call']} | {r['truth_inside_intervals']} of {r['intervals']} | "
            f"{', '.join(r['pairs']) or '-'} | {r['forecast_kind']} ({r['members']}) | "
            f"{f.get('P90', float('nan')):.4g} / {f.get('P50', float('nan')):.4g} / "
            f"{f.get('P10', float('nan')):.4g} ({f.get('truth') or float('nan'):.4g}) | "
            f"{'yes' if f.get('inside') else 'NO'} | {f.get('width') or float('nan'):.3f} | "
            + " | ".join("yes" if (r.get(q) or {}).get("inside") else "NO"
                         for q in ("FWPT", "FGPT")) + " |")
    df = pd.DataFrame(results.values())
    if len(df):
        n = len(df)
        held = int((df.truth_inside_intervals == df.intervals).sum())
        fopt = sum(bool((r.get("FOPT") or {}).get("inside")) for r in results.values())
        lines += ["", f"{n} cases: the truth inside all 95 % intervals in {held}; "
                  f"{int(df.truth_inside_intervals.sum())} of {int(df.intervals.sum())} "
                  f"intervals hold it; field cumulative oil inside P90-P10 in {fopt}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)))
    ap.add_argument("--budget", type=int, default=60)
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--table", action="store_true")
    args = ap.parse_args()
    results = json.loads(args.results.read_text()) if args.results.is_file() else {}
    if args.table:
        print(table(results))
        return
    out = args.out.resolve()
    store = ArtifactStore(out / "store")
    for seed in args.seeds:
        case = make_case(out, seed)
        name = f"synthetic-hidden-lm-b{args.budget}-d{args.draws}-{seed}"
        # always the command: a finished campaign resumes with no call, its posterior runs
        # (the Jacobian, the draws) made if they are not yet
        subprocess.run([str(Path(sys.executable).parent / "hmflow"), "run", "--case",
                        str(case), "--agent", "lm", "--budget", str(args.budget),
                        "--forecast-draws", str(args.draws), "--workers",
                        str(args.workers), "--seed", "0", "--campaign", name,
                        "--storage", str(out / "store")], check=True)
        found = figures(store, name)
        results[name] = found
        args.results.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.results.with_suffix(".tmp")
        tmp.write_text(json.dumps(results, indent=1, sort_keys=True))
        os.replace(tmp, args.results)
        print(f"{name}: {json.dumps(found)}")
    print(table(results))


if __name__ == "__main__":
    main()
