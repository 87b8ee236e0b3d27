"""The truth an ensemble run's report sets beside the ensembles, when the case knows it.

The truth (optional): a truth file beside the case file (:data:`TRUTH_FILES`).
``hidden_truth.json``, written by ``hmflow hide --kind field``, names one GRDECL of the
truth's fields (``truth_grdecl``) and the truth run's summary (``summary``), whose curves are
read as a member's are. ``truth.json``, the synthetic case's
(:data:`hmcore.scenarios.synthetic.TRUTH_NAME`), may map a field's name to a GRDECL
(``fields``) and names a CSV of the truth's responses (``files.truth_responses``: ``well,
days, quantity, value``), whose cumulatives are taken as given (FOPT, WOPT...) or integrated
from the rates as :func:`hmcore.simulation.curves.read_curves` does. A GRDECL holds the
truth's physical values under the field's keyword, over all cells or the active ones; files
are found as written or, failing that, by name in the case's folder. Either part may be
absent.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hmcore.fields.grdecl import read_grdecl
from hmcore.fields.spec import FieldSpec
from hmcore.fields.transform import to_update_space
from hmcore.scenarios.synthetic import TRUTH_NAME
from hmcore.simulation.curves import CUMULATIVE_OF, FIELD, FIELD_TOTAL, read_curves


@dataclass(frozen=True, eq=False)
class FieldTruth:
    """What is known of the truth: ``fields`` (name -> ``(n_active,)`` in update space) and
    ``curves`` (``well``, ``quantity``, ``days``, ``value``; None when unknown), read from
    ``source``."""

    fields: Mapping[str, np.ndarray]
    curves: pd.DataFrame | None
    source: str

    def digest(self) -> str:
        """sha256 of what the report shows of the truth (its fields and curves), so that a
        report is rebuilt when the truth file's content changes."""
        h = hashlib.sha256(self.source.encode())
        for name in sorted(self.fields):
            h.update(name.encode())
            h.update(np.ascontiguousarray(self.fields[name], np.float64).tobytes())
        if self.curves is not None:
            h.update(self.curves.to_csv(index=False).encode())
        return h.hexdigest()


def read_truth(case_file: Path | str, fields: tuple[FieldSpec, ...],
               dims: tuple[int, int, int], active: np.ndarray,
               wells: tuple[str, ...] = ()) -> FieldTruth | None:
    """The case's truth (see the module's docstring), or None when its folder holds no truth
    file or the file states neither fields nor responses. ValueError naming the file when a
    truth field's values do not fit the grid."""
    folder = Path(case_file).parent
    path = next((folder / n for n in TRUTH_FILES if (folder / n).is_file()), None)
    if path is None:
        return None
    doc = json.loads(path.read_text())
    named = doc.get("fields")
    grdecls = (dict(named) if isinstance(named, dict) else
               {f.name: doc["truth_grdecl"] for f in fields} if doc.get("truth_grdecl") else {})
    values: dict[str, np.ndarray] = {}
    for spec in fields:
        if grdecls.get(spec.name):
            values[spec.name] = _truth_field(_beside(path, grdecls[spec.name]), spec, dims,
                                             active)
    summary = _beside(path, doc["summary"]) if doc.get("summary") else None
    responses = _beside(path, (doc.get("files") or {}).get("truth_responses")
                        or "truth_responses.csv")
    if summary is not None and summary.is_file():
        curves = read_curves(summary, list(wells))
    elif responses.is_file():
        curves = truth_curves(pd.read_csv(responses))
    else:
        curves = None
    if not values and curves is None:
        return None
    return FieldTruth(values, curves, str(path))


TRUTH_FILES = ("hidden_truth.json", TRUTH_NAME)
"""The truth files looked for beside the case file, first found first: ``hmflow hide --kind
field``'s (``truth_grdecl``: one GRDECL of every field; ``summary``: the truth run's summary)
and the synthetic case's (``fields``: field name -> GRDECL; ``files.truth_responses``)."""


def _beside(truth_file: Path, name: str) -> Path:
    """A file a truth file names: as written (absolute, or relative to its folder), else the
    file of that name in its folder (a case folder moved since it was written)."""
    path = truth_file.parent / name
    return path if path.exists() else truth_file.parent / Path(name).name


def _truth_field(grdecl: Path, spec: FieldSpec, dims: tuple[int, int, int],
                 active: np.ndarray) -> np.ndarray:
    """A truth field from ``grdecl`` (physical values under the field's keyword, over all
    cells or the active ones) in update space on the active cells."""
    arrays = read_grdecl(grdecl)
    if spec.keyword not in arrays:
        raise ValueError(f"{grdecl}: no {spec.keyword} for field '{spec.name}'")
    v = arrays[spec.keyword]
    n_total = int(np.prod(dims))
    if v.size == n_total:
        v = v[np.asarray(active, np.int64)]
    if v.size != len(active):
        raise ValueError(f"{grdecl}: {v.size} values of {spec.keyword}; the grid has "
                         f"{n_total} cells, {len(active)} active")
    return to_update_space(np.clip(v, *spec.bounds), spec)


def truth_curves(responses: pd.DataFrame) -> pd.DataFrame:
    """A truth's responses (``well, days, quantity, value``) with its cumulatives: each
    well's WOPT, WWPT, WGPT as given or integrated from its rate (rate x step, a step ending
    at its row's day), and the field's totals as given or the sum over the wells."""
    r = responses[["well", "quantity", "days", "value"]].copy()
    frames = [r]
    for well, rows in r[r.well != FIELD].groupby("well", sort=False):
        have = set(rows.quantity)
        for total, rate in CUMULATIVE_OF.items():
            if total in have or rate not in have:
                continue
            s = rows[rows.quantity == rate].sort_values("days")
            steps = np.diff(np.concatenate([[0.0], s.days.to_numpy(float)]))
            frames.append(pd.DataFrame({"well": well, "quantity": total, "days": s.days,
                                        "value": np.cumsum(s.value.to_numpy(float) * steps)}))
    out = pd.concat(frames, ignore_index=True)
    for total, well_total in FIELD_TOTAL.items():
        if ((out.well == FIELD) & (out.quantity == total)).any():
            continue
        parts = out[(out.well != FIELD) & (out.quantity == well_total)]
        if len(parts):
            summed = parts.groupby("days", as_index=False)["value"].sum()
            out = pd.concat([out, summed.assign(well=FIELD, quantity=total)],
                            ignore_index=True)
    return out
