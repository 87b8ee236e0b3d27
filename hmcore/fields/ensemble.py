"""The ``[ensemble]`` section of a case file: how ES-MDA runs (Emerick & Reynolds 2013).

ERT's default weights 4, 2, 1 are normalised to the inflation factors 7, 3.5, 1.75, so that
sum(1/alpha) = 1: with a linear model and a Gaussian prior the assimilations then sample the
same posterior as one Kalman update (Emerick & Reynolds 2013, eq. 13). A member whose run
fails is left out of every later update, as in ERT, while at least ``minimum`` remain.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from hmcore.fields.spec import Count, Number, Section

ERT_WEIGHTS = (4.0, 2.0, 1.0)
"""ERT's default ES-MDA weights; normalised to inflation factors with sum(1/alpha) = 1."""


class EnsembleSpec(Section):
    """The ``[ensemble]`` section: ES-MDA's ensemble size, inflation weights (normalised so
    that sum(1/alpha) = 1), the fewest members that must run for an update (ERT's
    MIN_REALIZATIONS; hmflow's default is half the ensemble), localisation (``"adaptive"``:
    correlation thresholding, Vossepoel, Evensen & van Leeuwen 2025; ``"distance"``: a
    Gaspari-Cohn taper reaching 0 at ``radius`` from a datum's well, Emerick 2016) and the
    seed of the observation perturbations."""

    size: Count = Field(default=100, ge=2)
    weights: tuple[Number, ...] = Field(default=ERT_WEIGHTS, min_length=1)
    min_realizations: Count | None = None
    localisation: Literal["none", "adaptive", "distance"] = "none"
    radius: Number | None = None
    seed: Count = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> EnsembleSpec:
        if any(not w > 0 for w in self.weights):
            raise ValueError(f"inflation weights must all be > 0, got {list(self.weights)}")
        m = self.min_realizations
        if m is not None and not 2 <= m <= self.size:
            raise ValueError(f"min_realizations must lie in [2, size = {self.size}], got {m}")
        if self.localisation == "distance" and (self.radius is None or not self.radius > 0):
            raise ValueError(f"localisation = 'distance' needs radius > 0 (the distance, in "
                             f"the deck's length unit, where a datum's influence ends), got "
                             f"radius = {self.radius}")
        if self.localisation != "distance" and self.radius is not None:
            raise ValueError(f"radius = {self.radius} is only for localisation = 'distance', "
                             f"not {self.localisation!r}; remove it")
        return self

    @property
    def alphas(self) -> tuple[float, ...]:
        """Inflation factors: the weights scaled so that sum(1/alpha) = 1 (4, 2, 1 gives
        7, 3.5, 1.75)."""
        w = np.asarray(self.weights, float)
        return tuple(float(a) for a in w * np.sum(1.0 / w))

    @property
    def minimum(self) -> int:
        """The fewest members that must run for an update (``min_realizations``, else half
        the ensemble, at least 2)."""
        if self.min_realizations is not None:
            return self.min_realizations
        return max(2, math.ceil(self.size / 2))
