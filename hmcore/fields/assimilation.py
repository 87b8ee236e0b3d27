"""One ES-MDA run of a case's fields, step by step, on plain inputs: the prior ensemble, the
data the smoother sees, the members' responses from their run records, and the update.

The data are the noise-whitened residuals of the fitted history, as the campaign's methods
use them (:class:`hmcore.scoring.observations.ObservationSet`: ``(simulated - observed) /
sigma`` along each well's series, AR(1)-prewhitened): in that space the observations are 0
with unit, independent errors, so the smoother gets ``values = 0``, ``std = 1`` and, per
member, ``Y`` = its residual vector. This is the same noise the campaign weighs by, and a
linear map of the data, so ES-MDA's update is the one with the observations' own covariance.
A datum's location, for distance localisation, is its well's (the mean centre of the well's
connected cells); a row of no well (a field total) is not localised.

A member whose run failed (its record's ``status`` is ``FAIL``, with its ``failure`` kind) or
whose record has no residuals is left out of the update (:mod:`hmcore.fields.smoother`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from hmcore.errors import CaseError
from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.grid import FieldGrid
from hmcore.fields.layout import Layout
from hmcore.fields.members import scalar_prior
from hmcore.fields.prior import draw_prior
from hmcore.fields.realisations import read_realisations
from hmcore.fields.smoother import Observations, SmootherSettings, Update, assimilate
from hmcore.fields.spec import FieldSpec, FilesPrior


@dataclass(frozen=True, eq=False)
class Prior:
    """The prior ensemble ``X`` ``(size, layout.size)`` float32 in update space, its
    ``layout``, and what makes it reproducible (``seeds``: each drawn field's prior seed, the
    scalars' seed; ``sources``: each field's prior source, a files prior with its folder)."""

    X: np.ndarray
    layout: Layout
    seeds: Mapping[str, int]
    sources: Mapping[str, str]


def draw_ensemble(fields: Sequence[FieldSpec], grid: FieldGrid, size: int,
                  scalars: Sequence[str] = (), seed: int = 0) -> Prior:
    """The prior: every field's members (drawn by :func:`hmcore.fields.prior.draw_prior`, or
    the user's GRDECL files read by :func:`hmcore.fields.realisations.read_realisations`, a
    files prior's ``folder`` already resolved), then the scalars ``scalars`` uniform in their
    scaled coordinates (:func:`hmcore.fields.members.scalar_prior`, stream ``seed``).
    CaseError with every problem of the user's files."""
    given, problems = {}, []
    for f in fields:
        if isinstance(f.prior, FilesPrior):
            members, found = read_realisations(f, f.prior.folder, grid, size)
            problems += found
            if members is not None:
                given[f.name] = members
    if problems:
        raise CaseError(problems)
    drawn = draw_prior(tuple(fields), grid, size, given)
    layout = Layout(tuple(f.name for f in fields), tuple(scalars), grid.n_active)
    u = scalar_prior(size, scalars, seed)
    X = layout.stack(drawn.values, {n: u[:, k] for k, n in enumerate(scalars)})
    seeds = {**drawn.seeds, **({"scalars": seed} if scalars else {})}
    sources = {f.name: (f"files {f.prior.folder}" if isinstance(f.prior, FilesPrior)
                        else f.prior.source) for f in fields}
    return Prior(X, layout, seeds, sources)


def smoother_data(row_wells: Sequence[str], well_xy: Mapping[str, np.ndarray]
                  ) -> Observations:
    """The data as the smoother sees them (see the module's docstring): ``len(row_wells)``
    whitened residuals, 0 with std 1, located at their well (``well_xy[well]``, x and y; NaN
    for a well not in ``well_xy``)."""
    n = len(row_wells)
    nan = np.array([np.nan, np.nan])
    locations = np.array([np.asarray(well_xy.get(w, nan), float)[:2] for w in row_wells],
                         float).reshape(n, 2)
    return Observations(np.zeros(n), np.ones(n), locations)


def well_locations(grid: FieldGrid, connections: Mapping[str, Sequence[tuple[int, int, int]]]
                   ) -> dict[str, np.ndarray]:
    """x, y of each well: the mean centre of its connected cells (1-based i, j, k); a well
    with no active connected cell is left out."""
    out = {}
    for well, cells in connections.items():
        try:
            out[well] = grid.centre_of(list(cells))[:2]
        except ValueError:
            continue
    return out


def response_matrix(records: Mapping[int, dict], members: int, n_obs: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``(Y, failed)`` from the members' run records (member -> record): ``Y`` ``(members,
    n_obs)`` their ``residuals`` (NaN rows for a member without a record: not run, left out
    before), ``failed`` ``(members,)`` True for a record whose run failed or that has no
    residual vector of ``n_obs`` values."""
    Y = np.full((members, n_obs), np.nan)
    failed = np.zeros(members, bool)
    for m, record in records.items():
        residuals = record.get("residuals")
        if record.get("status") == "FAIL" or residuals is None or len(residuals) != n_obs:
            failed[m] = True
            continue
        Y[m] = np.asarray([np.nan if v is None else v for v in residuals], float)
    return Y, failed


def update(X: np.ndarray, records: Mapping[int, dict], data: Observations, iteration: int,
           spec: EnsembleSpec, locations: np.ndarray | None = None) -> Update:
    """ES-MDA update number ``iteration`` (0-based) of ``X`` with the members' records (see
    :func:`response_matrix`): failed members left out, TooFewRealizations below the
    ensemble's ``min_realizations``."""
    Y, failed = response_matrix(records, X.shape[0], data.values.shape[0])
    return assimilate(X, Y, data, iteration, SmootherSettings.of(spec), failed,
                      locations if spec.localisation == "distance" else None)


def misfit(record: dict) -> float:
    """A member's data misfit: the mean square of its whitened residuals (about 1 for a
    model that fits within noise; NaN for a failed run)."""
    r = record.get("residuals")
    if record.get("status") == "FAIL" or not r:
        return float("nan")
    values = np.asarray([np.nan if v is None else v for v in r], float)
    return float(np.mean(values ** 2))


def iteration_summary(iteration: int, planned: Sequence[int], records: Mapping[int, dict]
                      ) -> dict:
    """What one round of member runs gave: the members planned, run and failed (by failure
    kind, with the reason of each), and the misfit's median and mean over those that ran."""
    failed = {m: r for m, r in records.items() if r.get("status") == "FAIL"}
    misfits = np.array([misfit(r) for m, r in records.items() if m not in failed], float)
    misfits = misfits[np.isfinite(misfits)]
    kinds: dict[str, int] = {}
    for r in failed.values():
        kinds[str(r.get("failure"))] = kinds.get(str(r.get("failure")), 0) + 1
    return {"iteration": iteration, "planned": len(planned), "ran": len(records),
            "failed": len(failed), "failed_by_kind": kinds,
            "failures": {str(m): {"kind": r.get("failure"), "reason": r.get("reason")}
                         for m, r in sorted(failed.items())},
            "misfit_median": float(np.median(misfits)) if misfits.size else None,
            "misfit_mean": float(np.mean(misfits)) if misfits.size else None}
