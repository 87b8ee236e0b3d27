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


@dataclass(frozen=True)
class Nearest:
    """Per observed row (in the observed frame's order): whether a simulated record of the
    same well and quantity lies within the tolerance, and the nearest one's time and value
    (NaN where none does)."""

    matched: np.ndarray
    sim_days: np.ndarray
    value: np.ndarray


def nearest(observed: pd.DataFrame, simulated: pd.DataFrame, tolerance_days: float) -> Nearest:
    """The nearest simulated record (same well and quantity) of each observed row.

    ``observed``: well, quantity, days; ``simulated``: well, quantity, days, value. Times that
    coincide keep the later simulated record, whatever the row order; of two records equally
    far the earlier wins. The one nearest-time matcher of hmflow: :func:`align` pairs with it,
    the diagnosis's residual vectors read their simulated values from it.
    """
    m = len(observed)
    nan = np.full(m, np.nan)
    if simulated is None or simulated.empty or m == 0:
        return Nearest(np.zeros(m, bool), nan, nan.copy())
    sim = simulated.sort_index()
    s_code, o_code = _codes(sim, observed)
    t = sim["days"].to_numpy(float)
    v = sim["value"].to_numpy(float)
    od = observed["days"].to_numpy(float)
    # by (well, quantity), time, then row order; of records at the same time the last one
    order = np.lexsort((np.arange(len(t)), t, s_code))
    t, v, s_code = t[order], v[order], s_code[order]
    last = np.r_[(s_code[1:] != s_code[:-1]) | (t[1:] != t[:-1]), True]
    t, v, s_code = t[last], v[last], s_code[last]
    # one sorted axis for every (well, quantity): code * span + days, groups never overlap
    span = 2.0 * (max(np.abs(t).max(), np.abs(od).max()) + tolerance_days) + 1.0
    right = np.searchsorted(s_code * span + t, o_code * span + od)
    li = np.clip(right - 1, 0, len(t) - 1)
    ri = np.clip(right, 0, len(t) - 1)
    has_left = (right >= 1) & (s_code[li] == o_code)
    has_right = (right < len(t)) & (s_code[ri] == o_code)
    d_left = np.where(has_left, np.abs(od - t[li]), np.inf)
    d_right = np.where(has_right, np.abs(t[ri] - od), np.inf)
    idx = np.where(d_left <= d_right, li, ri)  # the earlier record wins a tie
    ok = np.minimum(d_left, d_right) <= tolerance_days + 1e-9
    return Nearest(ok, np.where(ok, t[idx], np.nan), np.where(ok, v[idx], np.nan))


def align(observed: pd.DataFrame, simulated: pd.DataFrame, tolerance_days: float) -> Alignment:
    """Pair each observed row with the nearest simulated row of the same well and quantity
    (:func:`nearest`).

    ``observed``: well, quantity, days, value (+ optional sigma, flowing, derived).
    ``simulated``: well, quantity, days, value. Both in the same units; days since START.
    """
    if simulated.empty or observed.empty:
        return Alignment(pd.DataFrame(columns=ALIGNED_COLUMNS), len(observed))
    obs = observed.sort_values(["well", "quantity"], kind="stable")  # grouped, row order kept
    near = nearest(obs, simulated, tolerance_days)
    ok = near.matched
    od = obs["days"].to_numpy(float)
    m = len(od)
    pairs = pd.DataFrame({
        "well": obs["well"].to_numpy()[ok], "quantity": obs["quantity"].to_numpy()[ok],
        "days": od[ok], "sim_days": near.sim_days[ok],
        "observed": obs["value"].to_numpy(float)[ok], "simulated": near.value[ok],
        "sigma": (obs["sigma"].to_numpy(float) if "sigma" in obs else np.full(m, np.nan))[ok],
        "flowing": (obs["flowing"].to_numpy(bool) if "flowing" in obs else np.ones(m, bool))[ok],
        "derived": (obs["derived"].to_numpy(bool) if "derived" in obs else np.zeros(m, bool))[ok],
    }, columns=ALIGNED_COLUMNS)
    return Alignment(pairs, len(observed))


def _codes(sim: pd.DataFrame, observed: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """One integer per row for its (well, quantity), shared by the two frames; -1 for an
    observed row whose well or quantity is never simulated."""
    w_sim, wells = pd.factorize(sim["well"].astype(str))
    q_sim, quantities = pd.factorize(sim["quantity"].astype(str))
    w_obs = pd.Index(wells).get_indexer(observed["well"].astype(str))
    q_obs = pd.Index(quantities).get_indexer(observed["quantity"].astype(str))
    n_q = max(len(quantities), 1)
    o_code = np.where((w_obs >= 0) & (q_obs >= 0), w_obs * n_q + q_obs, -1)
    return w_sim * n_q + q_sim, o_code
