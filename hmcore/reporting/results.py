"""Evaluation records -> one flat table (one row per simulator call, failed ones included)."""

from __future__ import annotations

import pandas as pd

from hmcore.scoring.misfit import PRIMARY
from hmcore.scoring.record_format import upgrade

COLUMNS = ["index", "phase", "lane", "status", "failure", "reason", "E", "likelihood", "penalty",
           "reward", "coverage",
           "E_heldout", "wall_time_s", "sim_time_s", "peak_rss_bytes", "run_dir", "seed", "agent",
           "attempts"]



def results_table(records: list[dict], parameter_names: list[str], objective: str = "E"
                  ) -> pd.DataFrame:
    """Columns: COLUMNS (``likelihood``: the campaign's final noise's, when consolidated with
    it), ``p_<name>`` (physical values), ``a_<name>`` (actions in [-1, 1]),
    ``loss_<category>`` (per-response misfit), ``violation_kinds`` (the physics checks a penalised
    call broke, comma-separated), ``macro_nmse/r2/cmatch``, ``best_E_so_far`` and
    ``best_objective_so_far`` (the running best of ``objective``, the column that chooses)."""
    rows = []
    for r in sorted((upgrade(r) for r in records), key=lambda r: r["index"]):
        row = {c: r.get(c) for c in COLUMNS}
        for k, name in enumerate(parameter_names):
            row[f"p_{name}"] = (r.get("params") or {}).get(name)
            action = r.get("action") or []
            row[f"a_{name}"] = action[k] if k < len(action) else None
        for cat in PRIMARY:
            row[f"loss_{cat}"] = (r.get("per_response") or {}).get(cat)
        row["violation_kinds"] = ",".join(r.get("violation_kinds") or [])
        macro = (r.get("metrics") or {}).get("macro") or {}
        for k in ("nmse", "r2", "cmatch"):
            row[f"macro_{k}"] = macro.get(k)
        rows.append(row)
    df = pd.DataFrame(rows)
    for col in df.columns:
        if col not in ("phase", "status", "failure", "reason", "run_dir", "agent",
                       "violation_kinds"):
            df[col] = pd.to_numeric(df[col], errors="coerce")
    df["best_E_so_far"] = running_best(df["E"], df["status"])
    df["best_objective_so_far"] = running_best(df[objective], df["status"])
    return df


def running_best(E: pd.Series, status: pd.Series, groups: list[pd.Series] | None = None
                 ) -> pd.Series:
    """The best (lowest) E of the COMPLETE calls so far, in the series' order (per group when
    ``groups`` are given); failed and penalised calls never count, and the best is carried
    over them (NaN only before the first valid call)."""
    valid = E.where(status == "COMPLETE")
    if not groups:
        return valid.cummin().ffill()
    return valid.groupby(groups).cummin().groupby(groups).ffill()
