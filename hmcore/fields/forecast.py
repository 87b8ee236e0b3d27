"""The forecast of an ensemble of field models: P90 / P50 / P10 at the schedule's end, of the
prior and of the posterior, and every member's value.

Every member's run covers the whole schedule, so the prior ensemble's runs (the first
assimilation's) and the posterior's (the run after the last update) are the forecast, with no
run of their own. The quantities and the exceedance convention are the campaign's
(:func:`hmcore.simulation.forecast.forecast_table`: field cumulative oil, water and gas, each
well's cumulative oil; P90 the low case, 90 % of members at or above it). A member whose run
failed has no curves and is not counted.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import pandas as pd

from hmcore.simulation.curves import FIELD, value_at_end
from hmcore.simulation.forecast import FIELD_QUANTITIES, WELL_QUANTITIES, forecast_table

ENSEMBLES = ("prior", "posterior")


def ensemble_forecast(curves: Mapping[str, Mapping[int, pd.DataFrame]], wells: Sequence[str]
                      ) -> pd.DataFrame:
    """One row per ensemble (``prior``, ``posterior``: the keys of ``curves`` present) and
    quantity: ``ensemble`` and :func:`~hmcore.simulation.forecast.forecast_table`'s columns.
    ``curves[ensemble]``: member -> that run's curves."""
    frames = [forecast_table(dict(curves[e]), list(wells)).assign(ensemble=e)
              for e in ENSEMBLES if curves.get(e)]
    if not frames:
        return pd.DataFrame(columns=["ensemble", *forecast_table({}, []).columns])
    table = pd.concat(frames, ignore_index=True)
    return table[["ensemble", *[c for c in table.columns if c != "ensemble"]]]


def member_values(curves: Mapping[str, Mapping[int, pd.DataFrame]], wells: Sequence[str]
                  ) -> pd.DataFrame:
    """Every member's value at the schedule's end: ``ensemble``, ``member``, ``well`` (FIELD
    or a well), ``quantity``, ``value``."""
    targets = [(FIELD, q) for q in FIELD_QUANTITIES] + [(w, q) for w in wells
                                                        for q in WELL_QUANTITIES]
    rows = [{"ensemble": e, "member": m, "well": w, "quantity": q,
             "value": value_at_end(c, w, q)}
            for e in ENSEMBLES if e in curves for m, c in sorted(curves[e].items())
            for w, q in targets]
    return pd.DataFrame(rows, columns=["ensemble", "member", "well", "quantity", "value"])


def headline(table: pd.DataFrame, quantity: str = "FOPT", well: str = FIELD) -> str:
    """``FOPT P90/P50/P10: prior 1.2e+06/1.3e+06/1.4e+06, posterior ...`` (one line; '' when
    the table has no such row)."""
    parts = []
    for e in ENSEMBLES:
        row = table[(table.ensemble == e) & (table.well == well) & (table.quantity == quantity)]
        if len(row):
            r = row.iloc[0]
            parts.append(f"{e} {r.P90:.4g}/{r.P50:.4g}/{r.P10:.4g} ({int(r.members)} members)")
    return f"{quantity} P90/P50/P10: " + ", ".join(parts) if parts else ""
