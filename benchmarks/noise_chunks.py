"""How the length of the stretches a line is fitted to biases the noise estimate (issue 47).

    python benchmarks/noise_chunks.py [--replicates 200] [--seed 0]

The estimator (:func:`hmcore.scoring.noise.fit_noise`) fits a line to every stretch of at
most :data:`hmcore.scoring.noise.CHUNK_ROWS` rows (6) of a run and estimates the level and
the AR(1) correlation from the contrasts free of it (REML). On observed values the short
stretches keep a trend or a step out of the noise; on residuals against a fitted model (the
refinement, :meth:`hmcore.scoring.observations.ObservationSet.refine`) the simulator has taken
the signal out, and a line over 6 rows also takes out the slow part of a correlated noise.
Here pure AR(1) series (no signal), 4 wells pooled as one group, are estimated with
stretches of 6 rows and with whole runs (``NoiseSeries.chunk_rows = None``), for several run
lengths and correlations: the median of the estimated level over the true one (1) and of the
estimated correlation, with the 10th-90th percentiles of the level. No simulation; seconds.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hmcore.scoring.noise import CHUNK_ROWS, NoiseSeries, fit_noise  # noqa: E402


def ar1(rng: np.random.Generator, n: int, rho: float) -> np.ndarray:
    """A stationary unit-variance AR(1) series ``(n,)``."""
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0]
    for t in range(1, n):
        x[t] = rho * x[t - 1] + np.sqrt(1.0 - rho ** 2) * e[t]
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--replicates", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print("| rows per run | true rho | stretch | level / true: median (10th-90th) | rho: median |")
    print("|---|---|---|---|---|")
    for rows in (12, 30, 60):
        for rho in (0.0, 0.35, 0.7):
            for chunk in (CHUNK_ROWS, None):
                rng = np.random.default_rng([args.seed, rows, int(rho * 100)])
                level, corr = [], []
                for _ in range(args.replicates):
                    series = [NoiseSeries(ar1(rng, rows, rho), chunk_rows=chunk)
                              for _ in range(4)]
                    fit = fit_noise(series, groups=[0] * 4)
                    level.append(np.nanmedian(fit.sigma))
                    corr.append(fit.rho)
                lo, mid, hi = np.percentile(level, [10, 50, 90])
                print(f"| {rows} | {rho:g} | {chunk or 'whole run'} | {mid:.2f} ({lo:.2f}-{hi:.2f}) "
                      f"| {np.median(corr):.2f} |")


if __name__ == "__main__":
    main()
