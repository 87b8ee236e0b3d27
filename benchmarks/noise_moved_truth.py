"""The noise estimated from moved_truth.py's histories, against the noise that made them, and
what it makes of the truth: no simulation once the truth's run is kept.

    python benchmarks/noise_moved_truth.py --out bench-moved [--truths 1]
        [--generators white-laplace ar1-laplace] [--levels 0.5 1 2]

The histories are ``benchmarks/moved_truth.py``'s (``make_case``: the same truths, noise and
seeds; ``OUT/truth-<seed>/truth_responses.csv`` is read when it exists, else the truth is run
once, as moved_truth.py does). Each case goes through
:meth:`hmcore.scoring.observations.ObservationSet.from_case`, as a campaign's does. Per case
and quantity (BHP, GOR, water cut; fitted rows): the noise model the estimate chose, the
estimated / true sigma over rows (median, 10th and 90th percentiles, least), the largest
distance of the truth from an observed row in estimated sigma, and the truth's chi2 / n (the
whitened residuals of the noise-free responses: about 1 when the noise is right).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))

from moved_truth import BHP_BAR, GENERATORS, REL, make_case

from hmcore.cases import load_case
from hmcore.scoring.observations import ObservationSet

QUANTITIES = ("WBHP", "WGOR", "WWCT")


def measure(case_file: Path, truth: pd.DataFrame, level: float) -> list[dict]:
    """Per quantity: the noise model, estimated / true sigma over the fitted rows, the truth's
    largest distance in sigma and its chi2 / n."""
    obs = ObservationSet.from_case(load_case(case_file))
    rows = obs.rows
    sim = obs.simulated(truth)
    true = np.where(rows.quantity == "WBHP", level * BHP_BAR, level * REL * np.abs(sim))
    z = (sim - rows.observed.to_numpy(float)) / rows.sigma.to_numpy(float)
    white = obs.whiten(z, "fit")
    idx = obs.vector_index("fit")
    q_of = rows.quantity.to_numpy()[idx]
    out = []
    for q in QUANTITIES:
        pick = idx[q_of == q]
        if not pick.size:
            continue
        ratio = rows.sigma.to_numpy(float)[pick] / true[pick]
        ratio = ratio[np.isfinite(ratio) & (ratio > 0)]
        out.append({"quantity": q, "model": obs.noise_report.get(q, {}).get("noise_model", "-"),
                    "median": float(np.median(ratio)), "p10": float(np.percentile(ratio, 10)),
                    "p90": float(np.percentile(ratio, 90)), "least": float(ratio.min()),
                    "max_z": float(np.nanmax(np.abs(z[pick]))),
                    "chi2_n": float(np.sum(white[q_of == q] ** 2) / pick.size)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--truths", type=int, nargs="+", default=[1])
    ap.add_argument("--generators", nargs="+", default=list(GENERATORS))
    ap.add_argument("--levels", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    args = ap.parse_args()
    print("| truth | generator | level | quantity | model | est / true: median (p10-p90), "
          "least | truth's largest distance (sigma) | truth's chi2 / n |")
    print("|---|---|---|---|---|---|---|---|")
    for seed in args.truths:
        for gen in args.generators:
            for level in args.levels:
                case = make_case(args.out, seed, gen, level)
                truth = pd.read_csv(args.out / f"truth-{seed}" / "truth_responses.csv")
                for r in measure(case, truth, level):
                    print(f"| {seed} | {gen} | x{level:g} | {r['quantity']} | {r['model']} | "
                          f"{r['median']:.2f} ({r['p10']:.2g}-{r['p90']:.2g}), "
                          f"{r['least']:.2g} | {r['max_z']:.3g} | {r['chi2_n']:.3g} |")


if __name__ == "__main__":
    main()
