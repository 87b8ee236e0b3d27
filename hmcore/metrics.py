"""Reported match metrics: NMSE, R^2 and C_match per response, per well, and category macro.

``NMSE = sum (y - yhat)^2 / (sum y^2 + eps)``, ``R^2 = 1 - SS_res / SS_tot``,
``C_match = 100 / (1 + NMSE)``. Categories: oil, water, gas, bhp (primary; their mean is the
macro) and the diagnostics gor and wct.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from hmcore.misfit import DIAGNOSTIC, PRIMARY

EPS = 1e-12
CATEGORIES = {"oil": PRIMARY["oil"], "water": PRIMARY["water"], "gas": PRIMARY["gas"],
              "bhp": PRIMARY["bhp"], **DIAGNOSTIC}


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


def score(y: np.ndarray, yhat: np.ndarray) -> dict:
    e = nmse(y, yhat) if len(y) else float("nan")
    return {"n": int(len(y)), "nmse": e, "r2": r2(y, yhat) if len(y) else float("nan"),
            "cmatch": cmatch(e) if len(y) else float("nan")}


def _nanmean(values: list[float]) -> float:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


def compute_metrics(pairs: pd.DataFrame) -> dict:
    """``{macro, categories, wells}`` from aligned pairs (quantity, well, observed, simulated)."""
    categories = {}
    wells: dict[str, dict] = {}
    for cat, q in CATEGORIES.items():
        sub = pairs[pairs.quantity == q]
        categories[cat] = score(sub["observed"].to_numpy(), sub["simulated"].to_numpy())
        for well, g in sub.groupby("well"):
            wells.setdefault(str(well), {})[cat] = score(g["observed"].to_numpy(),
                                                          g["simulated"].to_numpy())
    macro = {k: _nanmean([categories[c][k] for c in PRIMARY]) for k in ("nmse", "r2", "cmatch")}
    return {"macro": macro, "categories": categories, "wells": wells}


def category_table(metrics: dict) -> pd.DataFrame:
    """The paper's category table: rows oil, water, gas, bhp, gor, wct, macro."""
    cats = metrics["categories"]
    rows = [{"category": c, "N": cats[c]["n"], "NMSE": cats[c]["nmse"], "R2": cats[c]["r2"],
             "C_match": cats[c]["cmatch"]} for c in CATEGORIES if c in cats]
    mac = metrics["macro"]
    rows.append({"category": "macro (oil, water, gas, bhp)",
                 "N": sum(metrics["categories"][c]["n"] for c in PRIMARY),
                 "NMSE": mac["nmse"], "R2": mac["r2"], "C_match": mac["cmatch"]})
    return pd.DataFrame(rows)


def well_table(metrics: dict) -> pd.DataFrame:
    """The paper's well x response table of C_match (%)."""
    rows = []
    for well, cats in sorted(metrics["wells"].items(), key=lambda kv: _natural(kv[0])):
        rows.append({"well": well, **{c: cats.get(c, {}).get("cmatch", float("nan"))
                                      for c in CATEGORIES}})
    return pd.DataFrame(rows, columns=["well", *CATEGORIES])


def _natural(name: str) -> tuple:
    """Sort key so that PRO-4 comes before PRO-11."""
    import re

    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name))
