"""Measured well history: read and validate the long CSV, derive water and gas rates.

Columns: ``well, quantity, value`` and ``days`` or ``date`` (required), and ``sigma, units,
flowing`` (optional). A ``date`` (``2015-01-21`` or Eclipse's ``21 JAN 2015``) counts from the
deck's START; given with ``days``, the two must agree within a day. Quantities: WBHP, WOPR/WWPR/WGPR, WGOR, WWCT (fraction) and, for injectors,
WWIR/WGIR. Values are in the deck's units unless the ``units`` column names another unit of the
same dimension (``psia``, ``stb/day``, ``Mscf/day``...): value and sigma are then converted
(see :mod:`hmcore.units`); an unknown or mismatched unit is refused with the deck's unit named.
Every problem is reported at once with the CSV line number (header = line 1).
"""

from __future__ import annotations

import difflib
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd

from hmcore.errors import CaseError, Problem
from hmcore.simulation.responses import QUANTITIES
from hmcore.units import deck_unit, factor_to_deck

REQUIRED = ("well", "quantity", "value")  # and days or date
OPTIONAL = ("sigma", "date", "units", "flowing")
NON_NEGATIVE = ("WOPR", "WWPR", "WGPR", "WGOR", "WWCT", "WWIR", "WGIR")


def read_observed(path: Path, unit_system: str | None = None,
                  start: datetime | None = None) -> pd.DataFrame:
    """Read ``path`` and return the validated table (with derived WWPR/WGPR rows when needed).

    Columns of the result: well, days, quantity, value, sigma (NaN when unknown),
    flowing (bool), derived (bool), line (CSV line number, -1 for derived rows).
    ``unit_system`` is the deck's (METRIC, FIELD, LAB, PVT-M): rows whose ``units`` names
    another unit are converted into it; without it, units are only checked to be known.
    Raises CaseError listing every problem.
    """
    table, problems = inspect_observed(path, unit_system, start)
    if problems:
        raise CaseError(problems)
    return table


def inspect_observed(path: Path, unit_system: str | None = None, start: datetime | None = None
                     ) -> tuple[pd.DataFrame | None, list[Problem]]:
    """The table as far as it can be read (rows with problems included) and every problem.

    The table is None when the file cannot be read at all; derived rows are added only when
    there is no problem.
    """
    try:
        return _read(Path(path), unit_system, start), []
    except CaseError as exc:
        return getattr(exc, "table", None), exc.problems


def _read(path: Path, unit_system: str | None, start: datetime | None) -> pd.DataFrame:
    if not path.is_file():
        raise CaseError([Problem(str(path), "observed history file not found",
                                 "check the 'observed' key of the case file")])
    try:
        # only an empty cell is missing: a well named NA stays NA, a sigma "None" is not a
        # number (pandas would read both as missing)
        raw = pd.read_csv(path, dtype={"well": str, "quantity": str}, skipinitialspace=True,
                          keep_default_na=False, na_values=[""])
    except Exception as exc:
        raise CaseError([Problem(str(path), f"cannot read as CSV: {exc}",
                                 "save it as comma-separated text with a header row")]) from exc
    raw.columns = [c.strip().lower() for c in raw.columns]
    for column in ("value", "sigma", "days"):  # TRUE/FALSE cells are read as booleans,
        if column in raw and raw[column].dtype in (bool, object):  # which would pass as 1, 0
            raw[column] = raw[column].map(
                lambda v: str(v) if isinstance(v, (bool, np.bool_)) else v)
    missing = [c for c in REQUIRED if c not in raw.columns]
    if "days" not in raw.columns and "date" not in raw.columns:
        missing.append("days (or date)")
    if missing:
        raise CaseError([Problem(str(path), f"missing column(s) {missing}; found "
                                 f"{list(raw.columns)}", f"the header must contain "
                                 f"{list(REQUIRED)} and days or date")])
    problems: list[Problem] = []
    days = (pd.to_numeric(raw["days"], errors="coerce").astype(float) if "days" in raw
            else pd.Series(np.nan, index=raw.index))
    if "date" in raw:
        days, date_problems = _days_from_dates(raw, days, start, path)
        problems += date_problems
    problems += _text_column_problems(raw, path)
    df = pd.DataFrame({
        "well": raw["well"].map(lambda w: "" if pd.isna(w) else str(w).strip()),
        "quantity": raw["quantity"].astype(str).str.strip().str.upper(),
        "days": days,
        "value": pd.to_numeric(raw["value"], errors="coerce").astype(float),
        "sigma": (pd.to_numeric(raw["sigma"], errors="coerce").astype(float) if "sigma" in raw
                  else np.nan),
        "flowing": _flowing(raw),
        "line": np.arange(len(raw)) + 2,
    })

    problems += _convert_units(df, raw, path, unit_system)

    def report(mask: pd.Series, what: str, fix: str) -> None:
        for _, row in df[mask].iterrows():
            problems.append(Problem(f"{path} line {row.line}",
                                    what.format(**{k: row[k] for k in df.columns}), fix))

    for _, row in df[~df.quantity.isin(QUANTITIES)].iterrows():
        near = difflib.get_close_matches(row.quantity, list(QUANTITIES), n=1)
        problems.append(Problem(f"{path} line {row.line}", f"unknown quantity '{row.quantity}'"
                                + (f" (did you mean {near[0]!r}?)" if near else ""),
                                f"use one of {list(QUANTITIES)}"))
    report(df.well == "", "the well is empty", "name the well of every row")
    report(df.days.isna(), "days is not a number (and no date gives it)",
           "write the time in days since START, or a date like 2015-01-21")
    report(df.days < 0, "days={days} is negative", "days count from the deck's START date")
    report(df.value.isna() | ~np.isfinite(df.value.fillna(0)), "value is missing, NaN or infinite",
           "remove the row or give a number")
    report(df.quantity.isin(NON_NEGATIVE) & (df.value < 0),
           "negative {quantity} value {value}", "rates, GOR and water cut must be >= 0")
    report((df.quantity == "WWCT") & (df.value > 1), "water cut {value} > 1",
           "WWCT is a fraction in [0, 1]")
    report((df.quantity == "WBHP") & (df.value <= 0), "non-positive pressure {value}",
           "WBHP must be > 0 (absolute pressure)")
    if "sigma" in raw:
        report(df.sigma.notna() & (df.sigma <= 0), "sigma={sigma} must be > 0",
               "leave sigma empty when unknown")
        report(df.sigma.notna() & ~np.isfinite(df.sigma.fillna(0)), "sigma={sigma} is not "
               "finite", "give a positive number, or leave sigma empty when unknown")
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


def _convert_units(df: pd.DataFrame, raw: pd.DataFrame, path: Path,
                   unit_system: str | None) -> list[Problem]:
    """Convert value and sigma of rows with a ``units`` entry into the deck's unit (in place);
    a problem per (quantity, unit) that cannot be converted, naming its lines."""
    if "units" not in raw:
        return []
    units = raw["units"].map(lambda u: "" if pd.isna(u) else str(u).strip())
    system = unit_system or "METRIC"  # without a deck: check the names only
    problems = []
    named = (units != "") & df.quantity.isin(QUANTITIES)
    for (q, unit), grp in df[named].groupby([df.quantity[named], units[named]]):
        try:
            factor = factor_to_deck(q, unit, system)
        except ValueError as exc:
            lines = list(grp.line)
            where = f"{path} line{'s' if len(lines) > 1 else ''} " + ", ".join(
                map(str, lines[:8])) + (f" (+{len(lines) - 8} more)" if len(lines) > 8 else "")
            fix = (f"write {q} in {deck_unit(q, system)} (this deck's unit) or in a unit "
                   "listed above" if unit_system else "use a unit listed above")
            problems.append(Problem(where, str(exc), fix))
            continue
        if unit_system is not None and factor != 1.0:
            df.loc[grp.index, "value"] = df.loc[grp.index, "value"] * factor
            df.loc[grp.index, "sigma"] = df.loc[grp.index, "sigma"] * factor
    return problems


def parse_dates(values: pd.Series) -> pd.Series:
    """ISO dates (``2015-01-21``, with a time or not) or Eclipse's ``21 JAN 2015`` /
    ``21-JAN-2015``; NaT where none fits."""
    text = values.map(lambda v: "" if pd.isna(v) else str(v).strip())
    iso = text.where(text.str.match(r"^\d{4}-\d{2}-\d{2}"))
    try:  # a time zone is taken into UTC, then dropped (START has none)
        out = pd.to_datetime(iso, errors="coerce", format="ISO8601", utc=True)
    except (ValueError, TypeError):
        out = pd.Series(pd.NaT, index=text.index, dtype="datetime64[ns, UTC]")
    out = out.dt.tz_convert(None)
    eclipse = text.str.upper().str.replace("JLY", "JUL", regex=False)  # Eclipse's July
    for fmt in ("%d %b %Y", "%d-%b-%Y"):
        rest = out.isna() & (text != "")
        if rest.any():
            out[rest] = pd.to_datetime(eclipse[rest].str.title(), errors="coerce", format=fmt)
    return out


def _days_from_dates(raw: pd.DataFrame, days: pd.Series, start: datetime | None, path: Path
                     ) -> tuple[pd.Series, list[Problem]]:
    """Days from the date column where days is empty; dates that disagree with days by more
    than a day, or that cannot be read, are problems."""
    given = raw["date"].notna() & (raw["date"].astype(str).str.strip() != "")
    dates = parse_dates(raw["date"])
    problems = []
    bad = given & dates.isna()
    for i in np.flatnonzero(bad.to_numpy())[:20]:
        problems.append(Problem(f"{path} line {i + 2}", f"date '{raw['date'].iat[i]}' cannot "
                                "be read", "write dates as 2015-01-21 or 21 JAN 2015"))
    if start is None:
        if (days.isna() & given).any():
            problems.append(Problem(str(path), "dates without days need the deck's START date, "
                                    "and the deck could not be read", "fix the deck first"))
        return days, problems
    from_dates = (dates - pd.Timestamp(start)).dt.total_seconds() / 86400.0
    out = days.where(days.notna(), from_dates)
    clash = days.notna() & from_dates.notna() & ((days - from_dates).abs() > 1.0)
    for i in np.flatnonzero(clash.to_numpy())[:20]:
        problems.append(Problem(f"{path} line {i + 2}", f"days={days.iat[i]:g} but date "
                                f"{raw['date'].iat[i]} is day {from_dates.iat[i]:g} from the "
                                f"deck's START {start.date()}",
                                "correct one of them, or drop the date column"))
    return out, problems


FLOWING_TRUE = ("1", "true", "yes", "1.0")
FLOWING_FALSE = ("0", "false", "no", "0.0")


def _flowing(raw: pd.DataFrame) -> pd.Series:
    """The flowing column as booleans (an empty cell: flowing); other words are reported by
    :func:`_text_column_problems`."""
    if "flowing" not in raw:
        return pd.Series(True, index=raw.index)
    return raw["flowing"].map(lambda v: pd.isna(v) or str(v).strip().lower() not in FLOWING_FALSE)


def _text_column_problems(raw: pd.DataFrame, path: Path) -> list[Problem]:
    """Cells of the optional columns that are not what they must be: a sigma that is not a
    number, a flowing flag that is not one of true/false/1/0/yes/no."""
    problems = []
    if "sigma" in raw:
        given = raw["sigma"].map(lambda v: not pd.isna(v) and str(v).strip() != "")
        bad = given & pd.to_numeric(raw["sigma"], errors="coerce").isna()
        for i in np.flatnonzero(bad.to_numpy()):
            problems.append(Problem(f"{path} line {i + 2}", f"sigma {raw['sigma'].iat[i]!r} is "
                                    "not a number", "give a positive number, or leave sigma "
                                    "empty when unknown"))
    if "flowing" in raw:
        words = raw["flowing"].map(lambda v: "" if pd.isna(v) else str(v).strip().lower())
        bad = ~words.isin(("",) + FLOWING_TRUE + FLOWING_FALSE)
        for i in np.flatnonzero(bad.to_numpy()):
            problems.append(Problem(f"{path} line {i + 2}", f"flowing {raw['flowing'].iat[i]!r} "
                                    "is not a yes/no value", "write true, false, 1, 0, yes or no "
                                    "(or leave it empty: flowing)"))
    return problems


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
