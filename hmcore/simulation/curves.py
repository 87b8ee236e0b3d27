"""Simulated curves of one run, whole schedule: what the report draws and the forecast sums.

One tidy table per run, columns ``well`` (a well name, or ``FIELD``), ``quantity``, ``days``,
``value``, ``unit`` (as the summary file states it: SM3/DAY, BARSA, STB/DAY, PSIA...). Per well: the matched responses (WBHP, WOPR, WWPR, WGPR, WGOR, WWCT, see
:mod:`hmcore.simulation.responses`) and the cumulatives WOPT, WWPT, WGPT; for the field FOPT, FWPT, FGPT.
A cumulative the summary does not hold is integrated from its rate (an Eclipse rate is the
average over the step that ends at its time, so the cumulative is the sum of rate x step), and
a missing field total is the sum of the wells'. Nothing here runs a simulator.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from hmcore.simulation.responses import QUANTITIES, TIME_DECIMALS

FIELD = "FIELD"
CUMULATIVE_OF = {"WOPT": "WOPR", "WWPT": "WWPR", "WGPT": "WGPR"}
FIELD_TOTAL = {"FOPT": "WOPT", "FWPT": "WWPT", "FGPT": "WGPT"}


def read_curves(summary_path: Path, wells: list[str]) -> pd.DataFrame:
    """The curves of ``wells`` and the field totals from ``CASE.SMSPEC`` (see the module)."""
    from opm.io.ecl import ESmry

    smry = ESmry(str(summary_path))
    keys = set(smry.keys())
    days = np.round(np.asarray(smry["TIME"], dtype=float), TIME_DECIMALS)
    steps = np.diff(np.concatenate([[0.0], days]))
    frames = []

    def add(well: str, quantity: str, values, unit: str) -> None:
        frames.append(pd.DataFrame({"well": well, "quantity": quantity, "days": days,
                                    "value": np.asarray(values, dtype=float), "unit": unit}))

    def unit_of(key: str) -> str:
        return smry.units(key).strip() if key in keys else ""

    per_well: dict[str, dict[str, np.ndarray]] = {}
    units: dict[str, str] = {}
    for well in wells:
        got = per_well.setdefault(well, {})
        for q in (*QUANTITIES, *CUMULATIVE_OF):
            if f"{q}:{well}" in keys:
                got[q] = np.asarray(smry[f"{q}:{well}"], dtype=float)
                units[q] = units.get(q) or unit_of(f"{q}:{well}")
        for total, rate in CUMULATIVE_OF.items():
            if total not in got and rate in got:
                got[total] = np.cumsum(got[rate] * steps)
                units[total] = units.get(total) or _per_day_removed(units.get(rate, ""))
        for q, values in got.items():
            add(well, q, values, units.get(q, ""))
    for total, well_total in FIELD_TOTAL.items():
        if total in keys:
            add(FIELD, total, smry[total], unit_of(total))
        else:
            parts = [got[well_total] for got in per_well.values() if well_total in got]
            if parts:
                add(FIELD, total, np.sum(parts, axis=0), units.get(well_total, ""))
    if not frames:
        return empty()
    return pd.concat(frames, ignore_index=True)


def _per_day_removed(rate_unit: str) -> str:
    return rate_unit.upper().replace("/DAY", "").replace("/D", "")


def empty() -> pd.DataFrame:
    return pd.DataFrame({"well": pd.Series(dtype=str), "quantity": pd.Series(dtype=str),
                         "days": pd.Series(dtype=float), "value": pd.Series(dtype=float),
                         "unit": pd.Series(dtype=str)})


def value_at_end(curves: pd.DataFrame, well: str, quantity: str) -> float:
    """The last value of one curve (NaN when the run has no such curve)."""
    sel = curves[(curves.well == well) & (curves.quantity == quantity)]
    return float(sel.sort_values("days")["value"].iloc[-1]) if len(sel) else float("nan")
