"""Reported match metrics, the reference paper's formulas: NMSE, R^2 and C_match per response,
per well, and the macro over the primary categories.

``NMSE = sum (y - yhat)^2 / (sum y^2 + eps)``, ``R^2 = 1 - SS_res / SS_tot``,
``C_match = 100 / (1 + NMSE)``. Categories: oil, water, gas, bhp (primary) and the diagnostics
gor and wct. Macro NMSE and macro R^2 are the means over the primary categories with data;
macro C_match is ``100 / (1 + macro NMSE)`` (the paper's 97.23 = 100 / 1.0285), not the mean of
the categories' C_match.

GOR = Qg/Qo and WCT = Qw/(Qw+Qo) are defined only where their denominator is positive: a
record is left out when the observed denominator is 0 (the well is shut in: observed oil rate,
or liquid rate, 0; without an observed rate at that time, the ``flowing`` flag says so) or the
simulated one is 0; ``excluded`` counts them per category, well and reason.
"""

from __future__ import annotations

import math
from enum import Enum

import numpy as np
import pandas as pd

from hmcore.ordering import natural_key
from hmcore.scoring.misfit import DIAGNOSTIC, PRIMARY

EPS = 1e-12
CATEGORIES = {"oil": PRIMARY["oil"], "water": PRIMARY["water"], "gas": PRIMARY["gas"],
              "bhp": PRIMARY["bhp"], **DIAGNOSTIC, "water_inj": PRIMARY["water_inj"],
              "gas_inj": PRIMARY["gas_inj"]}
OPTIONAL = ("water_inj", "gas_inj")  # shown only when the history has them


def nmse(y: np.ndarray, yhat: np.ndarray) -> float:
    y, yhat = np.asarray(y, float), np.asarray(yhat, float)
    return float(np.sum((y - yhat) ** 2) / (np.sum(y ** 2) + EPS))


def r2(y: np.ndarray, yhat: np.ndarray) -> float:
    """Coefficient of determination; NaN when y has no variance (R^2 is undefined then)."""
    y, yhat = np.asarray(y, float), np.asarray(yhat, float)
    ss_tot = float(np.sum((y - y.mean()) ** 2)) if y.size else 0.0
    if ss_tot <= EPS:
        return float("nan")
    return 1.0 - float(np.sum((y - yhat) ** 2)) / ss_tot


def cmatch(nmse_value: float) -> float:
    return 100.0 / (1.0 + nmse_value)


def worst_well_cmatch(metrics: dict) -> float:
    """The lowest C_match of any well (its macro NMSE over the primary categories), from a
    :func:`compute_metrics` document; NaN when it has no well."""
    worst = float("nan")
    for cats in (metrics.get("wells") or {}).values():
        e = _nanmean([cats[c]["nmse"] for c in PRIMARY if c in cats])
        if math.isfinite(e):
            worst = cmatch(e) if math.isnan(worst) else min(worst, cmatch(e))
    return worst


def score(y: np.ndarray, yhat: np.ndarray) -> dict:
    e = nmse(y, yhat) if len(y) else float("nan")
    return {"n": int(len(y)), "nmse": e, "r2": r2(y, yhat) if len(y) else float("nan"),
            "cmatch": cmatch(e) if len(y) else float("nan")}


def _nanmean(values: list[float]) -> float:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


RATIO_DENOMINATORS = {"WGOR": ("WOPR",), "WWCT": ("WOPR", "WWPR")}


class Exclusion(str, Enum):
    """Why a GOR or water-cut record is left out of the metrics."""

    SHUT_IN_OBSERVED = "shut_in_observed"    # observed denominator 0: the ratio is undefined
    NO_RATE_SIMULATED = "no_rate_simulated"  # simulated denominator 0: no simulated ratio


def ratio_exclusions(pairs: pd.DataFrame) -> np.ndarray:
    """Per pair (in order): the :class:`Exclusion` value of a GOR / WCT record left out, else
    None. The denominator's rates are the pairs of its parts at the same well and day (the
    first such pair); a part with no observed value there leaves it to the ``flowing`` flag.
    ``pairs`` as :func:`hmcore.scoring.alignment.align` makes them (string wells, finite days)."""
    reason = np.full(len(pairs), None, dtype=object)
    quantity = pairs["quantity"].astype(str).to_numpy(object)
    if not np.isin(quantity, list(RATIO_DENOMINATORS)).any():
        return reason
    well = pairs["well"].astype(str).to_numpy(object)
    days = pairs["days"].to_numpy(float)
    y, yhat = pairs["observed"].to_numpy(float), pairs["simulated"].to_numpy(float)
    flowing = pairs["flowing"].astype(bool).to_numpy()
    first: dict[tuple, int] = {}  # (quantity, well, day) -> its first pair
    for i in range(len(pairs)):
        first.setdefault((quantity[i], well[i], days[i]), i)
    for q, parts in RATIO_DENOMINATORS.items():
        for i in np.flatnonzero(quantity == q):
            obs_den = sim_den = 0.0
            known = True  # all its rates observed; else the flowing flag
            for part in parts:
                j = first.get((part, well[i], days[i]))
                if j is None or np.isnan(y[j]):
                    known = False
                else:
                    obs_den += y[j]
                if j is not None and not np.isnan(yhat[j]):
                    sim_den += yhat[j]
            shut = obs_den <= 0 if known else not flowing[i]
            if shut:
                reason[i] = Exclusion.SHUT_IN_OBSERVED.value
            elif known and sim_den <= 0:
                reason[i] = Exclusion.NO_RATE_SIMULATED.value
    return reason


def compute_metrics(pairs: pd.DataFrame) -> dict:
    """``{macro, categories, wells, excluded}`` from aligned pairs (quantity, well, days,
    observed, simulated, flowing: as :func:`hmcore.scoring.alignment.align` makes them, string wells,
    finite days); ``excluded[cat][well][reason]`` counts the GOR / WCT records left out (each
    category's and well's score also carries ``n_excluded``); wells in sorted order."""
    categories = {}
    wells: dict[str, dict] = {}
    excluded: dict[str, dict[str, dict[str, int]]] = {}
    reasons = ratio_exclusions(pairs)
    # plain arrays: the loops below run per category and well on every simulator call
    quantity = pairs["quantity"].astype(str).to_numpy(object)
    well_of = pairs["well"].astype(str).to_numpy(object)
    y, yhat = pairs["observed"].to_numpy(float), pairs["simulated"].to_numpy(float)
    has_reason = reasons != None  # noqa: E711 (element-wise)
    for cat, q in CATEGORIES.items():
        rows = quantity == q
        if cat in OPTIONAL and not rows.any():
            continue  # injection rates: only for a history that has them
        left_out = rows & has_reason
        used = rows & ~left_out
        categories[cat] = score(y[used], yhat[used])
        if cat in DIAGNOSTIC:
            categories[cat]["n_excluded"] = int(left_out.sum())
            excluded[cat] = {}
            for well in sorted(set(well_of[left_out])):
                mine = left_out & (well_of == well)
                excluded[cat][well] = {str(why): int(np.sum(reasons[mine] == why))
                                       for why in sorted(set(reasons[mine]))}
        for well in sorted(set(well_of[rows])):
            mine = rows & (well_of == well)
            s = score(y[mine & ~left_out], yhat[mine & ~left_out])
            if cat in DIAGNOSTIC:
                s["n_excluded"] = int((mine & left_out).sum())
            wells.setdefault(well, {})[cat] = s
    return {"macro": macro_scores(categories, PRIMARY), "categories": categories,
            "wells": wells, "excluded": excluded}


def macro_scores(categories: dict, names) -> dict:
    """The paper's macro over the categories ``names`` that have data in ``categories`` (a
    :func:`compute_metrics` document's): the means of NMSE and R^2, and C_match = 100 / (1 +
    macro NMSE)."""
    macro = {k: _nanmean([categories[c][k] for c in names if c in categories])
             for k in ("nmse", "r2")}
    macro["cmatch"] = cmatch(macro["nmse"]) if math.isfinite(macro["nmse"]) else float("nan")
    return macro


def category_table(metrics: dict) -> pd.DataFrame:
    """The paper's category table: rows oil, water, gas, bhp, gor, wct, macro."""
    cats = metrics["categories"]
    rows = [{"category": c, "N": cats[c]["n"], "NMSE": cats[c]["nmse"], "R2": cats[c]["r2"],
             "C_match": cats[c]["cmatch"]} for c in CATEGORIES
            if c in cats and (c not in OPTIONAL or cats[c]["n"])]
    mac = metrics["macro"]
    rows.append({"category": "macro (" + ", ".join(macro_categories(metrics)) + ")",
                 "N": sum(cats[c]["n"] for c in PRIMARY if c in cats),
                 "NMSE": mac["nmse"], "R2": mac["r2"], "C_match": mac["cmatch"]})
    return pd.DataFrame(rows)


def macro_categories(metrics: dict) -> list[str]:
    """The categories the paper's macro of ``metrics`` averages, as its table names them: oil,
    water, gas, bhp and the injection rates the history has."""
    cats = metrics.get("categories") or {}
    return ["oil", "water", "gas", "bhp", *(c for c in OPTIONAL if cats.get(c, {}).get("n"))]


def well_table(metrics: dict) -> pd.DataFrame:
    """The paper's well x response table of C_match (%)."""
    rows = []
    for well, cats in sorted(metrics["wells"].items(), key=lambda kv: natural_key(kv[0])):
        rows.append({"well": well, **{c: cats.get(c, {}).get("cmatch", float("nan"))
                                      for c in CATEGORIES}})
    return pd.DataFrame(rows, columns=["well", *CATEGORIES])


def ratio_table(metrics: dict) -> pd.DataFrame:
    """The paper's GOR / water-cut diagnostics: per well and ratio, the records used and left
    out (by reason), NMSE, R^2 and C_match; a last row per ratio for all wells."""
    rows = []
    excluded = metrics.get("excluded", {})
    for cat in DIAGNOSTIC:
        for well, cats in sorted(metrics["wells"].items(), key=lambda kv: natural_key(kv[0])):
            if cat in cats:
                rows.append(_ratio_row(cat, well, cats[cat], excluded.get(cat, {}).get(well, {})))
        if cat in metrics["categories"]:
            total: dict[str, int] = {}
            for why in excluded.get(cat, {}).values():
                for k, n in why.items():
                    total[k] = total.get(k, 0) + n
            rows.append(_ratio_row(cat, "all", metrics["categories"][cat], total))
    return pd.DataFrame(rows, columns=["ratio", "well", "N", "excluded", "why", "NMSE", "R2",
                                       "C_match"])


def _ratio_row(cat: str, well: str, s: dict, why: dict[str, int]) -> dict:
    return {"ratio": cat, "well": well, "N": s["n"], "excluded": sum(why.values()),
            "why": ", ".join(f"{k} {n}" for k, n in sorted(why.items())),
            "NMSE": s["nmse"], "R2": s["r2"], "C_match": s["cmatch"]}

