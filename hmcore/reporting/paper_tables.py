"""The reference paper's three tables, with its columns and rounding, for any scored run.

1. match by category: N, NMSE, R^2, C_match (%) for oil, water, gas, BHP, GOR, WCT and the
   macro (the means of NMSE and R^2 over oil, water, gas, BHP; C_match = 100 / (1 + macro NMSE));
2. C_match (%) per well and category;
3. GOR / water-cut diagnostics per well: records used, records left out and why, NMSE, R^2,
   C_match.

NMSE and R^2 are rounded to 4 decimals and C_match to 2, as the paper prints them (0.0285,
0.9324, 97.23). The formulas are :mod:`hmcore.scoring.metrics`'s; :func:`metrics_from_summary` rescores
a stored summary file with them, so the tables of any stored campaign are rebuilt with today's
formulas without a simulator call.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from hmcore.scoring.alignment import align
from hmcore.scoring.metrics import category_table, compute_metrics, ratio_table, well_table
from hmcore.simulation.responses import read_responses

DECIMALS = {"NMSE": 4, "R2": 4, "C_match": 2}


def paper_tables(metrics: dict) -> dict[str, pd.DataFrame]:
    """``{"categories", "wells", "ratios"}``: the three tables, rounded as the paper."""
    wells = well_table(metrics)
    return {"categories": _rounded(category_table(metrics)),
            "wells": wells.round({c: DECIMALS["C_match"] for c in wells.columns if c != "well"}),
            "ratios": _rounded(ratio_table(metrics))}


def _rounded(df: pd.DataFrame) -> pd.DataFrame:
    return df.round({c: d for c, d in DECIMALS.items() if c in df.columns})


def metrics_from_summary(observed: pd.DataFrame, summary: Path, wells: list[str],
                         tolerance_days: float, history_end_days: float | None
                         ) -> tuple[dict, dict]:
    """Metrics of a stored run (its ``.SMSPEC``) on the fitted and the held-back history."""
    responses = read_responses(Path(summary), wells)
    if history_end_days is None:
        fit, held = observed, observed.iloc[0:0]
    else:
        fit = observed[observed.days <= history_end_days]
        held = observed[observed.days > history_end_days]
    heldout = compute_metrics(align(held, responses, tolerance_days).pairs) if len(held) else {}
    return compute_metrics(align(fit, responses, tolerance_days).pairs), heldout


def markdown(tables: dict[str, pd.DataFrame], title: str = "Match quality") -> str:
    """The three tables as Markdown, in the paper's rounding (n/a for an undefined value)."""
    parts = [(f"{title}: categories", "categories"),
             (f"{title}: C_match (%) per well and category", "wells"),
             (f"{title}: GOR and water cut per well (records used, left out and why)", "ratios")]
    return "\n".join(f"### {head}\n\n{markdown_table(tables[key])}\n" for head, key in parts)


def cell(column: str, v) -> str:
    """One table value as the paper prints it (C_match columns of the well table: 2 decimals)."""
    if v is None:  # a score with no record (stored as JSON null)
        return "n/a"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "n/a"
        return f"{v:.{DECIMALS.get(column, 2)}f}"
    return str(v)


def markdown_table(df: pd.DataFrame) -> str:
    """``df`` as a Markdown table, each value as :func:`cell` prints it."""
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    sep = "|" + "|".join("---" for _ in df.columns) + "|"
    rows = ["| " + " | ".join(cell(c, v) for c, v in zip(df.columns, row)) + " |"
            for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *rows])
