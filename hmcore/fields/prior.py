"""Prior members of field parameters, drawn zone by zone on the active cells.

Every zone (a range of layers or a region's cells, :class:`~hmcore.fields.spec.Zone`) of a
geostatistical field gets a Gaussian random field of variance 1, its *normal score* ``z``, at
the cells' centres with the zone's gstools covariance model
(:mod:`hmcore.fields.covariance`), then ``u = mean + std * z`` in update space. The vertical
coordinate is stratigraphic: a cell's depth is replaced by its layer's mean depth, so that a
dipping layer stays one correlated layer and ``ranges[2]`` is the correlation across layers.

Fields drawn from another field (its *source*):

* relation: ``u = intercept + slope * u_src + scatter * z_res`` (PUNQ-S3's
  ``log10(kh) = 0.77 + 9.02 phi`` with scatter; Floris et al. 2001);
* co-simulation: ``z = rho z_src + sqrt(1 - rho^2) z_new`` (collocated co-simulation with one
  covariance), then the target's zones' mean and std.

A geostatistical field and the fields drawn from it, directly or through others, form a
*family*: ``z_res`` and ``z_new`` have the family's covariance, drawn with the same
per-member azimuths (so that a channel's porosity and permeability stay aligned); white noise
when the source is the user's files. Member ``m`` of a field is drawn from
``default_rng([seed, m])``, the same member for a seed whatever the ensemble size, so
``start`` draws members beyond an ensemble (a hidden truth that is none of its members).

A zone of at most :data:`EXACT_LIMIT` cells is drawn exactly, ``z = R e`` with ``R`` the root of
its correlation matrix (one factorisation per zone, or per member and zone when the azimuth is
drawn, shared by the family). A larger zone is drawn by gstools' randomisation method
(``SRF``, 1000 modes, resampled by MCMC for every member: about 0.2 s a member and zone).

Arrays: ``(members, n_active)`` float32 per field, in update space, cells in
:class:`~hmcore.fields.grid.FieldGrid`'s active order.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import gstools as gs
import numpy as np

from hmcore.fields.covariance import correlation_root, covariance_model
from hmcore.fields.fieldset import draw_order
from hmcore.fields.grid import FieldGrid
from hmcore.fields.spec import (
    CosimulationPrior,
    FieldSpec,
    FilesPrior,
    GeostatisticalPrior,
    RelationPrior,
    Variogram,
    Zone,
)
from hmcore.fields.zones import zone_mask

EXACT_LIMIT = 2000
"""Zones of at most this many active cells are drawn exactly (see the module's docstring)."""
Structure = tuple[tuple[np.ndarray, Variogram], ...]
"""Cells (a boolean mask over the active cells) and their variogram, zone by zone."""


@dataclass(frozen=True, eq=False)
class PriorEnsemble:
    """Drawn members: ``values[name]`` ``(members, n_active)`` float32 in update space;
    ``scores[name]`` the normal scores of geostatistical and co-simulated fields (float32,
    same shape); ``seeds[name]`` each drawn field's seed; ``azimuths[name]`` the azimuth of
    every member and zone of its family, ``(members, zones)`` degrees; ``start``: the first
    member's index."""

    values: Mapping[str, np.ndarray]
    scores: Mapping[str, np.ndarray]
    seeds: Mapping[str, int]
    azimuths: Mapping[str, np.ndarray]
    start: int = 0

    @property
    def size(self) -> int:
        return int(next(iter(self.values.values())).shape[0]) if self.values else 0


def draw_prior(fields: list[FieldSpec] | tuple[FieldSpec, ...], grid: FieldGrid, size: int,
               given: Mapping[str, np.ndarray] | None = None, start: int = 0) -> PriorEnsemble:
    """Members ``start .. start+size-1`` of every field's prior (see the module's docstring).

    ``given`` holds the update-space members ``(size, n_active)`` of the fields whose prior is
    the user's files (:func:`hmcore.fields.realisations.read_realisations`). Check the fields
    first (:func:`hmcore.fields.fieldset.field_set_problems`,
    :func:`hmcore.fields.zones.prior_problems`)."""
    order = draw_order(fields)
    members = range(start, start + size)
    family = _families(order)
    normals: dict[str, np.ndarray] = {}
    azimuths: dict[str, np.ndarray] = {}
    for f in order:
        if family[f.name] == f.name:  # a geostatistical field: its family's normal fields
            kin = [g for g in order if family[g.name] == f.name]
            p = f.prior
            structure = tuple((zone_mask(z, grid), p.variogram_of(z)) for z in p.zones)
            zs, az = normal_scores(structure, grid, members, tuple(g.prior.seed for g in kin))
            normals.update((g.name, z) for g, z in zip(kin, zs))
            azimuths.update((g.name, az) for g in kin)
        elif family[f.name] is None and not isinstance(f.prior, FilesPrior):
            normals[f.name] = np.stack([np.random.default_rng([f.prior.seed, m])
                                        .standard_normal(grid.n_active) for m in members])
    values: dict[str, np.ndarray] = {}
    scores: dict[str, np.ndarray] = {}
    for f in order:
        p = f.prior
        z = None
        if isinstance(p, FilesPrior):
            if given is None or f.name not in given:
                raise ValueError(f"field '{f.name}': its prior is the user's files; pass "
                                 "them as given[name]")
            u = np.asarray(given[f.name], np.float64)
            if u.shape != (size, grid.n_active):
                raise ValueError(f"field '{f.name}': given members must have shape (size, "
                                 f"n_active) = ({size}, {grid.n_active}), got {u.shape}")
        elif isinstance(p, GeostatisticalPrior):
            z = normals[f.name]
            u = _scale(z, p.zones, grid)
        elif isinstance(p, RelationPrior):
            u = p.intercept + p.slope * values[p.from_].astype(np.float64) \
                + p.scatter * normals[f.name]
        else:
            assert isinstance(p, CosimulationPrior)
            rho = p.correlation
            z = rho * scores[p.from_].astype(np.float64) + math.sqrt(1 - rho ** 2) * normals[f.name]
            u = _scale(z, p.zones, grid)
        values[f.name] = u.astype(np.float32)
        if z is not None:
            scores[f.name] = z.astype(np.float32)
    seeds = {f.name: f.prior.seed for f in order if not isinstance(f.prior, FilesPrior)}
    return PriorEnsemble(values, scores, seeds, azimuths, start)


def normal_scores(structure: Structure, grid: FieldGrid, members: range,
                  seeds: tuple[int, ...]) -> tuple[list[np.ndarray], np.ndarray]:
    """One normal-score field ``(len(members), n_active)`` float64 per seed, all with the
    covariance of ``structure``, and the azimuths ``(len(members), zones)`` they were drawn
    with (drawn per member from the first seed's stream when a zone gives a range)."""
    zs = [np.zeros((len(members), grid.n_active)) for _ in seeds]
    azimuths = np.zeros((len(members), len(structure)))
    pos = stratigraphic_positions(grid)
    rngs = [[np.random.default_rng([seed, m]) for seed in seeds] for m in members]
    for col, (mask, variogram) in enumerate(structure):
        low, high = variogram.azimuth_range
        n = int(mask.sum())
        root, root_azimuth = None, None
        for row, streams in enumerate(rngs):
            azimuth = low if low == high else float(streams[0].uniform(low, high))
            azimuths[row, col] = azimuth
            model = covariance_model(variogram, azimuth)
            if n <= EXACT_LIMIT and root_azimuth != azimuth:
                root, root_azimuth = correlation_root(model, pos[:, mask]), azimuth
            for z, rng in zip(zs, streams):
                if n <= EXACT_LIMIT:
                    z[row, mask] = root @ rng.standard_normal(n)
                else:
                    z[row, mask] = gs.SRF(model, mean=0.0)(
                        pos[:, mask], seed=int(rng.integers(2 ** 31 - 1)),
                        mesh_type="unstructured", store=False)
    return zs, azimuths


def stratigraphic_positions(grid: FieldGrid) -> np.ndarray:
    """``(3, n_active)``: x, y and the mean depth of each cell's layer (see the module's
    docstring)."""
    k = grid.ijk[:, 2]
    depth_sum = np.bincount(k, weights=grid.centres[:, 2], minlength=grid.dims[2] + 1)
    counts = np.bincount(k, minlength=grid.dims[2] + 1)
    layer_depth = depth_sum / np.maximum(counts, 1)
    return np.vstack([grid.centres[:, 0], grid.centres[:, 1], layer_depth[k]])


def _families(order: list[FieldSpec]) -> dict[str, str | None]:
    """Each field's family: the name of the geostatistical field it is drawn from, directly
    or through others (None for the user's files and what is drawn from them)."""
    family: dict[str, str | None] = {}
    for f in order:
        if isinstance(f.prior, GeostatisticalPrior):
            family[f.name] = f.name
        elif isinstance(f.prior, FilesPrior):
            family[f.name] = None
        else:
            family[f.name] = family[f.prior.from_]
    return family


def _scale(z: np.ndarray, zones: tuple[Zone, ...], grid: FieldGrid) -> np.ndarray:
    """``mean + std * z`` zone by zone (float64)."""
    u = np.empty_like(z, dtype=np.float64)
    for zone in zones:
        mask = zone_mask(zone, grid)
        u[:, mask] = zone.mean + zone.std * z[:, mask]
    return u
