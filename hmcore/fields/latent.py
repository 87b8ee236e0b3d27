"""Latent actions: a case's fields moved by a handful of numbers, the leading modes of their
prior ensemble (issue 42; the reference paper's "structured spatial or latent actions").

The prior ensemble ``X`` ``(N, p)`` (the fields' columns of :class:`~hmcore.fields.layout.Layout`,
in update space: log10 permeability) is centred and scaled, ``A = (X - mean) / sqrt(N - 1)``,
and decomposed, ``A = U S V^T`` (principal component analysis of the ensemble, the discrete
Karhunen-Loeve expansion of the prior: Sarma, Durlofsky & Aziz 2008; Oliver, Reynolds & Liu
2008, ch. 6). A field is then

    x(z) = mean + sum_i z_i s_i v_i,      z_i ~ N(0, 1) a priori,

so that ``z`` drawn from the standard normal has the prior ensemble's mean and covariance
(truncated to the ``k`` modes kept). ``k`` is the fewest modes holding ``share`` of the prior's
variance (``sum s_i^2``), at most ``max_modes`` and at most ``N - 1``. The decomposition is of
the ``N x N`` Gram matrix ``A A^T`` (``eigh``), never of a ``p x p`` covariance: memory stays
``N x p`` whatever the grid's size.

The ``k`` coefficients are calibration parameters of kind ``latent`` (``mode_01``, ...,
:mod:`hmcore.model.latent_case`), bounded by ``[-bound, bound]`` (the prior's +-3 standard deviations by default): every scalar method
(``lm``, ``cmaes``, ``sac``...) moves them as it moves multipliers. With ``prior =
"regularised"`` (the default) the campaign's objective adds ``sum z_i^2`` to chi2 (the prior
as a regularisation: the maximum a posteriori of the coefficients, the objective of randomised
maximum likelihood, Oliver, He & Reynolds 1996, without its perturbations), so that a method
is not rewarded for fitting the noise with extreme fields; ``"box"`` keeps only the bounds.

Pure numpy; nothing here reads a deck or runs a simulator (the run is
:class:`hmcore.fields.members.LatentSimulator`'s).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator

from hmcore.fields.spec import Count, Number, Section

PREFIX = "mode_"
"""A latent parameter's name: ``mode_01``, ``mode_02``... (two digits up to 99 modes)."""


class LatentSpec(Section):
    """The ``[latent]`` section: the fields of the case are calibrated by the coefficients of
    their prior ensemble's leading modes (see the module's docstring). The prior ensemble is
    the one ``hmflow ensemble`` draws (``[ensemble]`` ``size`` and ``seed``): the same prior for
    both ways of matching the fields."""

    share: Number = Field(default=0.9, gt=0.0, le=1.0)
    max_modes: Count | None = Field(default=None, ge=1)
    bound: Number = Field(default=3.0, gt=0.0)
    prior: Literal["regularised", "box"] = "regularised"

    @model_validator(mode="after")
    def _check(self) -> LatentSpec:
        if self.max_modes is not None and self.max_modes > 999:
            raise ValueError(f"max_modes must be at most 999, got {self.max_modes}")
        return self


@dataclass(frozen=True, eq=False)
class LatentBasis:
    """The prior's mean ``(p,)`` and its leading modes ``(k, p)`` (mode i is ``s_i v_i``, in
    update space), with the share of the prior's variance they hold and how many modes the
    prior had (``available``: the nonzero singular values, at most N - 1)."""

    mean: np.ndarray
    modes: np.ndarray
    share: float
    available: int

    @property
    def k(self) -> int:
        return int(self.modes.shape[0])

    @property
    def names(self) -> tuple[str, ...]:
        """The coefficients' parameter names, ``mode_01`` ... (width 2, or 3 above 99)."""
        width = 2 if self.k < 100 else 3
        return tuple(f"{PREFIX}{i + 1:0{width}d}" for i in range(self.k))

    @classmethod
    def of_ensemble(cls, X: np.ndarray, share: float = 0.9,
                    max_modes: int | None = None) -> LatentBasis:
        """The basis of the prior ensemble ``X`` ``(N, p)`` (N >= 2 members, finite): the fewest
        leading modes holding ``share`` of its variance, at most ``max_modes``."""
        X = np.asarray(X, np.float64)
        if X.ndim != 2 or X.shape[0] < 2 or not np.isfinite(X).all():
            raise ValueError(f"the prior ensemble must be (members >= 2, parameters), finite; "
                             f"got shape {X.shape}")
        N = X.shape[0]
        mean = X.mean(axis=0)
        A = (X - mean) / np.sqrt(N - 1)
        lam, U = np.linalg.eigh(A @ A.T)           # ascending; A A^T = U S^2 U^T
        lam, U = lam[::-1], U[:, ::-1]
        total = float(lam.clip(min=0).sum())
        if not total > 0:
            raise ValueError("the prior ensemble has no spread: every member is the same")
        keep = lam > total * 1e-12                  # the nonzero modes (at most N - 1)
        lam, U = lam[keep], U[:, keep]
        held = np.cumsum(lam) / total
        k = int(np.searchsorted(held, share - 1e-12) + 1)
        k = min(k, lam.size, max_modes or lam.size)
        modes = U[:, :k].T @ A                      # row i: s_i v_i
        # a mode's sign is arbitrary (eigh's); fixed by its largest entry, positive
        top = np.abs(modes).argmax(axis=1)
        modes *= np.where(modes[np.arange(k), top] < 0, -1.0, 1.0)[:, None]
        return cls(mean, modes, float(held[k - 1]), int(lam.size))

    def fields(self, z: Sequence[float] | np.ndarray) -> np.ndarray:
        """The update-space values ``(p,)`` of coefficients ``z`` ``(k,)``."""
        z = np.asarray(z, np.float64)
        if z.shape != (self.k,):
            raise ValueError(f"z must have shape ({self.k},), got {z.shape}")
        return self.mean + z @ self.modes

    def project(self, x: np.ndarray) -> np.ndarray:
        """The coefficients ``(k,)`` whose field is nearest ``x`` ``(p,)`` (least squares:
        the modes are orthogonal, mode i of squared norm ``s_i^2``)."""
        d = np.asarray(x, np.float64) - self.mean
        return (self.modes @ d) / np.einsum("ij,ij->i", self.modes, self.modes)

    def values(self, params: Mapping[str, float]) -> np.ndarray:
        """The update-space values of a call's parameter values (its ``mode_*`` entries)."""
        missing = [n for n in self.names if n not in params]
        if missing:
            raise KeyError(f"the call has no value of {missing[:3]} (the basis has {self.k} "
                           "modes)")
        return self.fields([float(params[n]) for n in self.names])

    # ------------------------------------------------------------------ storage
    def table(self, rows: pd.DataFrame) -> pd.DataFrame:
        """The basis as a table: ``rows`` (``parameter``, ``cell`` of each of the p columns,
        as :func:`hmcore.fields.members.ensemble_table` labels them), ``mean`` and one float64
        column per mode; the share and ``available`` go to the artifact's manifest."""
        if len(rows) != self.mean.size:
            raise ValueError(f"{len(rows)} row labels for a basis of {self.mean.size} values")
        out = rows.reset_index(drop=True).copy()
        out["mean"] = self.mean
        for name, mode in zip(self.names, self.modes, strict=True):
            out[name] = mode
        return out

    @classmethod
    def from_table(cls, table: pd.DataFrame, share: float, available: int) -> LatentBasis:
        names = sorted(c for c in table.columns if c.startswith(PREFIX))
        modes = (np.stack([table[c].to_numpy(np.float64) for c in names]) if names
                 else np.zeros((0, len(table))))
        return cls(table["mean"].to_numpy(np.float64), modes, share, available)


def prior_residuals(params: Mapping[str, float], names: Sequence[str]) -> np.ndarray:
    """The prior's entries of a least-squares residual vector: the coefficients themselves
    (a priori standard normal), in ``names``' order; NaN where a value is missing."""
    return np.array([float(params.get(n, np.nan)) for n in names], float)
