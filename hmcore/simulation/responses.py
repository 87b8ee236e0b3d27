"""Simulated responses: an Eclipse summary (SMSPEC/UNSMRY) -> tidy table.

Table columns: ``well`` (str), ``days`` (float, days since START, rounded to 0.01 because the
summary stores TIME as float32), ``quantity`` (WBHP, WOPR, WWPR, WGPR, WGOR, WWCT; WWIR and WGIR for injectors) and
``value`` in the deck's units (bar, sm3/day, sm3/sm3, fraction in METRIC decks; see
:mod:`hmcore.units`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

QUANTITIES = ("WBHP", "WOPR", "WWPR", "WGPR", "WGOR", "WWCT", "WWIR", "WGIR")
INJECTION = ("WWIR", "WGIR")  # injectors' water and gas injection rates
TIME_DECIMALS = 2


def read_responses(summary_path: Path, wells: list[str] | None = None) -> pd.DataFrame:
    """Read well responses from ``CASE.SMSPEC``; ``wells=None`` means every well found."""
    from opm.io.ecl import ESmry

    smry = ESmry(str(summary_path))
    keys = set(smry.keys())
    days = np.round(np.asarray(smry["TIME"], dtype=float), TIME_DECIMALS)
    found = sorted({k.split(":", 1)[1] for k in keys if k.startswith("W") and ":" in k})
    frames = []
    for well in (wells if wells is not None else found):
        for q in QUANTITIES:
            key = f"{q}:{well}"
            if key in keys:
                frames.append(pd.DataFrame({"well": well, "days": days, "quantity": q,
                                            "value": np.asarray(smry[key], dtype=float)}))
    if not frames:
        return pd.DataFrame({"well": pd.Series(dtype=str), "days": pd.Series(dtype=float),
                             "quantity": pd.Series(dtype=str), "value": pd.Series(dtype=float)})
    return pd.concat(frames, ignore_index=True)


def last_time(summary_path: Path) -> float:
    """The last simulated time in days (to tell a run that stopped early)."""
    from opm.io.ecl import ESmry

    return float(np.round(np.asarray(ESmry(str(summary_path))["TIME"], dtype=float)[-1],
                          TIME_DECIMALS))
