"""Match simulated to observed records: per well and quantity, nearest simulated time.

An observation is matched when the nearest simulated time is within ``tolerance_days``;
others are left out and counted in the coverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

ALIGNED_COLUMNS = ["well", "quantity", "days", "sim_days", "observed", "simulated", "sigma",
                   "flowing", "derived"]


@dataclass(frozen=True)
class Alignment:
    """Matched pairs plus coverage (matched / observed rows)."""

    pairs: pd.DataFrame
    n_observed: int

    @property
    def n_matched(self) -> int:
        return len(self.pairs)

    @property
    def coverage(self) -> float:
        return self.n_matched / self.n_observed if self.n_observed else 0.0


def align(observed: pd.DataFrame, simulated: pd.DataFrame, tolerance_days: float) -> Alignment:
    """Pair each observed row with the nearest simulated row of the same well and quantity.

    ``observed``: well, quantity, days, value (+ optional sigma, flowing, derived).
    ``simulated``: well, quantity, days, value. Both in the same units; days since START.
    """
    # times that coincide after rounding keep the later record, whatever the row order
    sim_groups = {k: g.sort_values("days", kind="stable").drop_duplicates("days", keep="last")
                  for k, g in simulated.sort_index().groupby(["well", "quantity"])}
    pieces = []
    for key, obs in observed.groupby(["well", "quantity"], sort=True):
        sim = sim_groups.get(key)
        if sim is None or sim.empty:
            continue
        t = sim["days"].to_numpy(float)
        v = sim["value"].to_numpy(float)
        od = obs["days"].to_numpy(float)
        idx = np.clip(np.searchsorted(t, od), 1, len(t) - 1) if len(t) > 1 else np.zeros(len(od), int)
        if len(t) > 1:
            left_closer = np.abs(od - t[idx - 1]) <= np.abs(t[idx] - od)
            idx = np.where(left_closer, idx - 1, idx)
        ok = np.abs(t[idx] - od) <= tolerance_days + 1e-9
        if not ok.any():
            continue
        pieces.append(pd.DataFrame({
            "well": key[0], "quantity": key[1], "days": od[ok], "sim_days": t[idx][ok],
            "observed": obs["value"].to_numpy(float)[ok], "simulated": v[idx][ok],
            "sigma": (obs["sigma"].to_numpy(float) if "sigma" in obs else np.full(len(od), np.nan))[ok],
            "flowing": (obs["flowing"].to_numpy(bool) if "flowing" in obs else np.ones(len(od), bool))[ok],
            "derived": (obs["derived"].to_numpy(bool) if "derived" in obs else np.zeros(len(od), bool))[ok],
        }))
    pairs = pd.concat(pieces, ignore_index=True) if pieces else pd.DataFrame(columns=ALIGNED_COLUMNS)
    return Alignment(pairs, len(observed))
