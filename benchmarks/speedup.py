"""The 1-versus-W-worker speed-up, from the same campaigns run by two benchmarks.

    hmflow bench --case punqs3.toml --methods random,esmda,lm --seeds 1 --budget 100 \
        --workers 1 --name bench-punqs3-w1
    hmflow bench --case punqs3.toml --methods random,esmda,lm --seeds 1 --budget 100 \
        --workers 2 --name bench-punqs3-w2
    python benchmarks/speedup.py bench-punqs3-w1 bench-punqs3-w2 [--storage hmflow-storage]

Each argument is a benchmark's name in the store (its latest table) or a folder holding its
``runs.parquet`` (e.g. ``benchmarks/results/bench-punqs3-w1``). Prints one Markdown row per
method and seed that both ran: wall time with 1 worker and with W, the speed-up, the mean
simulator time per call of each (W runs at once on the same cores each take longer) and the
overhead of each (wall time over the simulator time per worker, less 1). ``random`` and
``esmda`` ask for the same points whatever W is, so their two campaigns make the same calls;
``lm`` sends W - 1 speculative Jacobian runs with each trial point, so its calls differ. Nothing
here is asserted; the figures go into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def runs_of(where: str, storage: Path) -> pd.DataFrame:
    from storage import ArtifactStore

    folder = Path(where)
    if (folder / "runs.parquet").is_file():
        return pd.read_parquet(folder / "runs.parquet")
    version = ArtifactStore(storage).latest(where, "benchmark")
    if version is None:
        raise SystemExit(f"{where}: neither a folder with runs.parquet nor a benchmark in "
                         f"{storage}; run hmflow bench first")
    return version.read_parquet("runs.parquet")


def main() -> None:
    from hmcore.reporting.benchmark import speedup

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("one", help="the 1-worker benchmark (name or folder)")
    ap.add_argument("many", help="the W-worker benchmark (name or folder)")
    ap.add_argument("--storage", type=Path, default=Path("hmflow-storage"))
    args = ap.parse_args()
    table = speedup(runs_of(args.one, args.storage), runs_of(args.many, args.storage))
    if table.empty:
        raise SystemExit("the two benchmarks share no (method, seed): nothing to compare")
    print("| method | seed | calls (1 / W) | wall min, 1 worker | wall min, W | speed-up | "
          "simulator s per call (1 / W) | overhead (1 / W) |")
    print("|---|---|---|---|---|---|---|---|")
    for d in table.to_dict("records"):
        print(f"| {d['method']} | {d['seed']} | {d['calls_1']} / {d['calls_w']} | "
              f"{d['wall_min_1']:.1f} | {d['wall_min_w']:.1f} | {d['speedup']:.2f} | "
              f"{d['sim_s_per_call_1']:.2f} / {d['sim_s_per_call_w']:.2f} | "
              f"{d['overhead_1']:+.0%} / {d['overhead_w']:+.0%} |")


if __name__ == "__main__":
    main()
