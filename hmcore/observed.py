"""Measured well history: read and validate the long CSV, derive water and gas rates.

Columns: ``well, days, quantity, value`` (required) and ``sigma, date, units, flowing``
(optional). Quantities: WBHP (bar), WOPR/WWPR/WGPR (sm3/day), WGOR (sm3/sm3), WWCT (fraction).
Every problem is reported at once with the CSV line number (header = line 1).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from hmcore.errors import CaseError, Problem
from hmcore.responses import QUANTITIES

REQUIRED = ("well", "days", "quantity", "value")
OPTIONAL = ("sigma", "date", "units", "flowing")
NON_NEGATIVE = ("WOPR", "WWPR", "WGPR", "WGOR", "WWCT")


def read_observed(path: Path) -> pd.DataFrame:
    """Read ``path`` and return the validated table (with derived WWPR/WGPR rows when needed).

    Columns of the result: well, days, quantity, value, sigma (NaN when unknown),
    flowing (bool), derived (bool), line (CSV line number, -1 for derived rows).
    Raises CaseError listing every problem.
    """
    table, problems = inspect_observed(path)
    if problems:
        raise CaseError(problems)
    return table


def inspect_observed(path: Path) -> tuple[pd.DataFrame | None, list[Problem]]:
    """The table as far as it can be read (rows with problems included) and every problem.

    The table is None when the file cannot be read at all; derived rows are added only when
    there is no problem.
    """
    try:
        return _read(Path(path)), []
    except CaseError as exc:
        return getattr(exc, "table", None), exc.problems


def _read(path: Path) -> pd.DataFrame:
    if not path.is_file():
        raise CaseError([Problem(str(path), "observed history file not found",
                                 "check the 'observed' key of the case file")])
    try:
        raw = pd.read_csv(path, dtype={"well": str, "quantity": str}, skipinitialspace=True)
    except Exception as exc:
        raise CaseError([Problem(str(path), f"cannot read as CSV: {exc}",
                                 "save it as comma-separated text with a header row")]) from exc
    raw.columns = [c.strip().lower() for c in raw.columns]
    missing = [c for c in REQUIRED if c not in raw.columns]
    if missing:
        raise CaseError([Problem(str(path), f"missing column(s) {missing}; found "
                                 f"{list(raw.columns)}", f"the header must contain {list(REQUIRED)}")])
    problems: list[Problem] = []
    df = pd.DataFrame({
        "well": raw["well"].astype(str).str.strip(),
        "quantity": raw["quantity"].astype(str).str.strip().str.upper(),
        "days": pd.to_numeric(raw["days"], errors="coerce"),
        "value": pd.to_numeric(raw["value"], errors="coerce"),
        "sigma": pd.to_numeric(raw["sigma"], errors="coerce") if "sigma" in raw else np.nan,
        "flowing": _flowing(raw),
        "line": np.arange(len(raw)) + 2,
    })

    def report(mask: pd.Series, what: str, fix: str) -> None:
        for _, row in df[mask].iterrows():
            problems.append(Problem(f"{path} line {row.line}",
                                    what.format(**{k: row[k] for k in df.columns}), fix))

    report(~df.quantity.isin(QUANTITIES), "unknown quantity '{quantity}'",
           f"use one of {list(QUANTITIES)}")
    report(df.days.isna(), "days is not a number", "write the time in days since START")
    report(df.days < 0, "days={days} is negative", "days count from the deck's START date")
    report(df.value.isna() | ~np.isfinite(df.value.fillna(0)), "value is missing, NaN or infinite",
           "remove the row or give a number")
    report(df.quantity.isin(NON_NEGATIVE) & (df.value < 0),
           "negative {quantity} value {value}", "rates, GOR and water cut must be >= 0")
    report((df.quantity == "WWCT") & (df.value > 1), "water cut {value} > 1",
           "WWCT is a fraction in [0, 1]")
    report((df.quantity == "WBHP") & (df.value <= 0), "non-positive pressure {value}",
           "WBHP must be > 0 (bar in a METRIC deck)")
    if "sigma" in raw:
        report(df.sigma.notna() & (df.sigma <= 0), "sigma={sigma} must be > 0",
               "leave sigma empty when unknown")
    dup = df.duplicated(["well", "days", "quantity"], keep=False) & df.days.notna()
    for (well, days, q), grp in df[dup].groupby(["well", "days", "quantity"]):
        problems.append(Problem(f"{path} lines {list(grp.line)}",
                                f"duplicate rows for well {well}, {q} at day {days}",
                                "keep one row per well, quantity and day"))
    if df.empty:
        problems.append(Problem(str(path), "no observations", "add at least one row"))
    if problems:
        error = CaseError(problems)
        error.table = df.assign(derived=False)
        raise error
    df["derived"] = False
    return derive_phase_rates(df)


def _flowing(raw: pd.DataFrame) -> pd.Series:
    if "flowing" not in raw:
        return pd.Series(True, index=raw.index)
    return raw["flowing"].map(lambda v: str(v).strip().lower() not in ("0", "false", "no", "0.0"))


def derive_phase_rates(df: pd.DataFrame) -> pd.DataFrame:
    """Add WWPR = WOPR*WWCT/(1-WWCT) and WGPR = WOPR*WGOR where they are missing.

    Derivation is per well and only when the well has no measured WWPR (WGPR) at all; rows are
    matched on the same day. Derived rows have ``derived=True`` and NaN sigma.
    """
    pieces = [df]
    wide = df.pivot_table(index=["well", "days"], columns="quantity", values="value")
    flowing = df.groupby(["well", "days"])["flowing"].all()
    for target, other, formula in (
        ("WWPR", "WWCT", lambda o, x: o * x / np.maximum(1.0 - x, 1e-6)),
        ("WGPR", "WGOR", lambda o, x: o * x),
    ):
        if "WOPR" not in wide or other not in wide:
            continue
        have = set(df.loc[df.quantity == target, "well"])
        sub = wide[["WOPR", other]].dropna()
        sub = sub[~sub.index.get_level_values("well").isin(have)]
        if sub.empty:
            continue
        pieces.append(pd.DataFrame({
            "well": sub.index.get_level_values("well"),
            "days": sub.index.get_level_values("days"),
            "quantity": target,
            "value": formula(sub["WOPR"].to_numpy(), sub[other].to_numpy()),
            "sigma": np.nan,
            "flowing": flowing.reindex(sub.index).to_numpy(),
            "line": -1,
            "derived": True,
        }))
    out = pd.concat(pieces, ignore_index=True)
    return out.sort_values(["well", "quantity", "days"], kind="stable").reset_index(drop=True)
