"""How a campaign spent its calls, from its journal: distinct points, points simulated more
than once, penalised calls, Jacobian runs that break a physics check their base passes, the
best E and the call that reached it, and the calls to 1.5x / 1.2x / 1.1x / 1x the floor.

    hmflow run --storage STORE                      # make run's campaign: 200 calls of lm
    python benchmarks/calls_spent.py STORE/synthetic-lm-v3-seed0 [--case synthetic] \
        [--floor 0.00286075]

Two calls are of the same point when every parameter agrees to ``--atol`` in scaled units
(default 1e-6, what the campaign's calls use: ``hmcore.calibration.calls.POINT_ATOL``); the
count at 1e-7 is printed too. The base of a Jacobian run is the latest earlier call that is
not a Jacobian run, one finite-difference step away along one coordinate. Nothing here is
asserted; the figures go into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hmcore.calibration.calls import POINT_ATOL
from hmcore.calibration.methods.lm import jacobian_base
from hmcore.cases import load_case


def repeats(u: np.ndarray, atol: float) -> tuple[int, list[int]]:
    """(distinct points, how many times each repeated point was simulated)."""
    first: dict[int, int] = {}
    for i in range(len(u)):
        for j in range(i):
            if j not in first and np.max(np.abs(u[i] - u[j])) <= atol:
                first[i] = j
                break
    counts: dict[int, int] = {}
    for j in first.values():
        counts[j] = counts.get(j, 1) + 1
    return len(u) - len(first), sorted(counts.values(), reverse=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("campaign", type=Path, help="a campaign's folder in the store")
    ap.add_argument("--case", default="synthetic")
    ap.add_argument("--floor", type=float, default=None, help="the floor E (the truth's)")
    ap.add_argument("--atol", type=float, default=POINT_ATOL)
    args = ap.parse_args()
    rows = [json.loads(p.read_text()) for p in sorted((args.campaign / "evaluations").glob(
        "*.json"))]
    space = load_case(args.case).space
    u = np.array([space.to_action(r["params"]) for r in rows])
    broken = [r["index"] + 1 for r in rows if r["phase"] == "jacobian" and (
        base := jacobian_base(r, rows)) is not None and set(r.get("violation_kinds") or ())
        - set(base.get("violation_kinds") or ())]
    valid = [r for r in rows if r["status"] == "COMPLETE" and r.get("E") is not None]
    best = min(valid, key=lambda r: r["E"])
    print(f"calls: {len(rows)}")
    for atol in (args.atol, 1e-7):
        n, times = repeats(u, atol)
        print(f"distinct points (to {atol:g}): {n}; repeated points simulated {times} times")
    print(f"penalised: {sum(r['status'] == 'INVALID' for r in rows)}; "
          f"failed: {sum(r['status'] == 'FAIL' for r in rows)}")
    print(f"Jacobian runs breaking a check their base passes: {len(broken)} (calls {broken})")
    print(f"best E {best['E']:.6g} at call {best['index'] + 1}")
    if args.floor:
        so_far, reached = np.inf, {}
        for r in rows:
            if r in valid:
                so_far = min(so_far, r["E"])
            for level in (1.5, 1.2, 1.1, 1.0):
                if level not in reached and so_far <= level * args.floor:
                    reached[level] = r["index"] + 1
        print("calls to " + ", ".join(f"{k}x the floor: {reached.get(k, 'never')}"
                                      for k in (1.5, 1.2, 1.1, 1.0)))


if __name__ == "__main__":
    main()
