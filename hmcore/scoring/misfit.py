"""The reference misfit E: equal-weight mean over BHP, oil, water and gas of range-normalised MSE
(and injectors' water and gas injection rates when the history has them).

For category c with matched pairs (y_obs, y_sim) pooled over wells,
``MSE_c = mean(((y_sim - y_obs) / range_c)^2)`` with ``range_c = max(y_obs) - min(y_obs)``
(falling back to ``max(|y_obs|, 1)`` for a flat record). ``E = mean_c MSE_c`` over the
categories that have data. The robust variant adds ``lambda * max`` over (well, category) of
the same normalised MSE, so one badly matched well cannot hide behind the average.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

PRIMARY = {"bhp": "WBHP", "oil": "WOPR", "water": "WWPR", "gas": "WGPR",
           "water_inj": "WWIR", "gas_inj": "WGIR"}  # injection: only when observed
DIAGNOSTIC = {"gor": "WGOR", "wct": "WWCT"}
CATEGORY_OF = {q: c for c, q in {**PRIMARY, **DIAGNOSTIC}.items()}


@dataclass(frozen=True)
class Misfit:
    E: float
    per_response: dict[str, float]
    per_well_response: dict[str, dict[str, float]] = field(default_factory=dict)
    variant: str = "mean"
    worst: float = float("nan")


def response_range(values: np.ndarray) -> float:
    """Normalising range of an observed record (never zero)."""
    if values.size == 0:
        return 1.0
    r = float(np.max(values) - np.min(values))
    return r if r > 1e-12 else max(float(np.max(np.abs(values))), 1.0)


def misfit(pairs: pd.DataFrame, variant: str = "mean", robust_lambda: float = 0.5,
           ranges: dict[str, float] | None = None) -> Misfit:
    """E from aligned pairs (columns quantity, well, observed, simulated).

    ``ranges`` fixes the normalising range per category (e.g. from the whole history so that
    fitted and held-back periods are on one scale); by default it comes from ``pairs``.
    Returns E = NaN when no primary category has a matched pair.
    """
    per_response: dict[str, float] = {}
    per_well: dict[str, dict[str, float]] = {}
    for cat, q in PRIMARY.items():
        sub = pairs[pairs.quantity == q]
        if sub.empty:
            continue
        rng = (ranges or {}).get(cat) or response_range(sub["observed"].to_numpy(float))
        z2 = ((sub["simulated"].to_numpy(float) - sub["observed"].to_numpy(float)) / rng) ** 2
        per_response[cat] = float(np.mean(z2))
        for well, idx in sub.groupby("well").indices.items():
            per_well.setdefault(str(well), {})[cat] = float(np.mean(z2[idx]))
    if not per_response:
        return Misfit(float("nan"), {}, {}, variant)
    E = float(np.mean(list(per_response.values())))
    worst = max(v for d in per_well.values() for v in d.values())
    if variant == "robust":
        E = E + robust_lambda * worst
    elif variant != "mean":
        raise ValueError(f"misfit variant must be 'mean' or 'robust', got {variant!r}")
    return Misfit(E, per_response, per_well, variant, worst)


def category_ranges(observed: pd.DataFrame) -> dict[str, float]:
    """Normalising range per primary category from an observed table (quantity, value)."""
    return {cat: response_range(observed.loc[observed.quantity == q, "value"].to_numpy(float))
            for cat, q in PRIMARY.items() if (observed.quantity == q).any()}
