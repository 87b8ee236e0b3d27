"""A case with a ``[latent]`` section as a calibration sees it: its fields replaced by the
coefficients of their prior's leading modes (:mod:`hmcore.fields.latent`), which stand first
in the parameter space, before the case's own scalar parameters.

:func:`latent_basis` draws the prior ensemble exactly as ``hmflow ensemble`` does (the fields'
priors, ``[ensemble]`` ``size`` and ``seed``), so that the two ways of matching the fields
start from one prior, and decomposes it; :func:`latent_case` gives the case its coefficients;
:func:`deck_coefficients` the coefficients nearest the deck's own fields (a campaign's
reference run "the deck as given" runs the basis's image of the deck, so that its record's
parameters are the ones it ran).
"""

from __future__ import annotations

import numpy as np

from hmcore.fields.assimilation import draw_ensemble
from hmcore.fields.grid import FieldGrid
from hmcore.fields.latent import LatentBasis, LatentSpec
from hmcore.fields.layout import Layout
from hmcore.fields.transform import to_update_space
from hmcore.model.case import Case
from hmcore.model.parameters import Parameter, ParameterKind, ParameterSpace


def latent_layout(case: Case, grid: FieldGrid) -> Layout:
    """The basis's columns: the case's fields, no scalar."""
    return Layout(tuple(f.name for f in case.fields), (), grid.n_active)


def latent_basis(case: Case, grid: FieldGrid) -> LatentBasis:
    """The basis of the case's prior ensemble (``[ensemble]`` size and seed; a files prior's
    realisations as given), holding ``[latent]`` ``share`` of its variance."""
    spec = case.latent or LatentSpec()
    prior = draw_ensemble(case.fields, grid, case.ensemble.size, (), case.ensemble.seed)
    return LatentBasis.of_ensemble(prior.X, spec.share, spec.max_modes)


def latent_parameters(basis: LatentBasis, spec: LatentSpec) -> tuple[Parameter, ...]:
    """The coefficients as calibration parameters: kind ``latent``, ``[-bound, bound]``."""
    return tuple(Parameter(name=n, kind=ParameterKind.LATENT, low=-spec.bound, high=spec.bound,
                           description=f"coefficient of the prior's mode {i + 1} of {basis.k} "
                                       f"({basis.share:.0%} of the prior's variance in all)")
                 for i, n in enumerate(basis.names))


def latent_case(case: Case, basis: LatentBasis) -> Case:
    """``case`` with the basis's coefficients, then its own scalars, as its parameter space;
    ValueError when a scalar's name is a coefficient's."""
    spec = case.latent or LatentSpec()
    coefficients = latent_parameters(basis, spec)
    clash = sorted(set(basis.names) & set(case.space.names))
    if clash:
        raise ValueError(f"case {case.name}: parameter name(s) {clash} are the latent "
                         "coefficients' own; rename them")
    return case.with_space(ParameterSpace(parameters=coefficients + case.space.parameters))


def latent_names(case: Case) -> tuple[str, ...]:
    """The names of the case's latent coefficients (none for a case without them)."""
    return tuple(p.name for p in case.space.parameters if p.kind == ParameterKind.LATENT)


def deck_coefficients(case: Case, grid: FieldGrid, basis: LatentBasis) -> np.ndarray:
    """The coefficients ``(k,)`` whose fields are nearest the deck's own (least squares in
    update space), clipped to ``[-bound, bound]``."""
    spec = case.latent or LatentSpec()
    x = np.concatenate([to_update_space(grid.deck_values(f.keyword), f) for f in case.fields])
    return np.clip(basis.project(x), -spec.bound, spec.bound)
