"""How often the physics penalty fires: uniform-random proposals in the case's parameter box.

    python benchmarks/bench_physics_penalty.py [--case CASE.toml | synthetic] [--n 10000] [--seed 0]

Without ``--case`` the PUNQ-S3 acceptance case (../shared/punqs3, the paper's five-parameter
box) is used. Draws ``--n`` actions uniformly in [-1, 1]^d (``numpy.random.default_rng(seed)``),
maps them to the box and runs :func:`hmcore.scoring.physics.check_physics` on each: the checks made
before any simulator time (kv/kh, porosity-permeability trend, pore volume, extremes). Prints
the share of proposals each check touches, the share touched by any, and the median penalty of
the penalised ones. The checks on simulated responses (minimum pressure, water cut range) need
a run each and are not counted here; a campaign's report counts them per call.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))


def main() -> None:
    from bench_evaluation import write_punq_case
    from hmcore.cases import load_case
    from hmcore.scoring.physics import check_physics

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default=None)
    ap.add_argument("--n", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    case = load_case(args.case or write_punq_case(Path(tempfile.mkdtemp())))
    rng = np.random.default_rng(args.seed)
    touched: collections.Counter = collections.Counter()
    penalties = []
    for _ in range(args.n):
        values = case.space.to_values(rng.uniform(-1.0, 1.0, case.space.dim))
        check = check_physics(values, case.space, case.info, case.physics)
        touched.update(set(check.kinds))
        penalties.append(check.penalty)
    pen = np.array(penalties)
    box = ", ".join(f"{p.name} [{p.low:g}, {p.high:g}]" for p in case.space.parameters)
    print(f"case {case.name}: {args.n} uniform proposals in {box}")
    for kind, n in touched.most_common():
        print(f"  {kind:<18} {100 * n / args.n:5.1f} %")
    print(f"  {'any':<18} {100 * np.mean(pen > 0):5.1f} %   median penalty of those "
          f"{np.median(pen[pen > 0]) if (pen > 0).any() else 0:.3f}")


if __name__ == "__main__":
    main()
