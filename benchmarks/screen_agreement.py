"""Do two screenings agree? Issue 44's check: the Morris rankings of two seeds (Spearman's rank
correlation over the top 10 of the first, on the case's objective) and the top 5 of Morris
against the OAT tornado's.

    python benchmarks/screen_agreement.py --storage STORE MORRIS_SEED0 MORRIS_SEED1 [--oat OAT]

Reads only the stored ``screening`` artifacts (no simulator call); prints one line per figure
and each screening's calls and wall time (first to last journaled call).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.stats import spearmanr

from storage import ArtifactStore, EvaluationJournal

TOP = 10
"""Spearman's correlation over the first screening's top TOP parameters."""
TOP_OAT = 5
"""The Morris top-5 against the tornado's top-5."""


def objective_ranks(store: ArtifactStore, name: str) -> dict[str, int]:
    """Parameter -> rank on the objective (1 = strongest) of the stored screening ``name``."""
    table = store.latest(name, "screening").read_parquet("ranking.parquet")
    rows = table[table.response == "objective"]
    return dict(zip(rows.parameter, rows["rank"].astype(int)))


def calls_and_wall(store: ArtifactStore, name: str) -> tuple[int, float]:
    rows = EvaluationJournal(store, name).rows()
    done = [r["finished_at"] for r in rows if r.get("finished_at")]
    return len(rows), (max(done) - min(done)) if done else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("first")
    parser.add_argument("second")
    parser.add_argument("--oat")
    parser.add_argument("--storage", default="./hmflow-storage")
    args = parser.parse_args()
    store = ArtifactStore(args.storage)
    a, b = objective_ranks(store, args.first), objective_ranks(store, args.second)
    top = sorted(a, key=a.get)[:TOP]
    rho = spearmanr([a[p] for p in top], [b[p] for p in top]).statistic
    print(f"Spearman over the top {len(top)} of {args.first}: {rho:.3f} "
          f"({'>=' if rho >= 0.8 else '<'} 0.8)")
    for name in (args.first, args.second, *([args.oat] if args.oat else [])):
        calls, wall = calls_and_wall(store, name)
        print(f"{name}: {calls} calls, {wall:.0f} s from the first to the last call")
    if args.oat:
        o = objective_ranks(store, args.oat)
        mine = set(top[:TOP_OAT])
        tornado = set(sorted(o, key=o.get)[:TOP_OAT])
        print(f"top {TOP_OAT} of {args.first} and of the tornado {args.oat}: "
              f"{len(mine & tornado)} in common ({', '.join(sorted(mine))} | "
              f"{', '.join(sorted(tornado))})")
    if not np.isfinite(rho):
        raise SystemExit("Spearman undefined (a ranking without ties' order?)")


if __name__ == "__main__":
    main()
