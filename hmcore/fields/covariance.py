"""A variogram as gstools' covariance model, and the exact square root of its correlation
matrix over a set of cells.

Ranges are practical ranges (GSLIB's convention, Deutsch & Journel 1998): the distance where
the correlation falls to 5 %, or for the spherical model where it reaches 0. gstools states a
model by a length scale, so the length scale is the range divided by the distance at which
the model with length scale 1 has correlation 0.05. Anisotropy and rotation are gstools':
``anis = [minor/major, vertical/major]``, the major axis ``azimuth`` degrees clockwise from the
y axis (north) is gstools' angle ``90 - azimuth`` counter-clockwise from x.
"""

from __future__ import annotations

import functools
import math

import gstools as gs
import numpy as np
from scipy.linalg import LinAlgError, cholesky
from scipy.optimize import brentq
from scipy.spatial.distance import cdist

from hmcore.fields.spec import Variogram

PRACTICAL_CORRELATION = 0.05
"""A range is where the correlation falls to 5 % (the spherical model's, where it is 0)."""
MODELS = {"gaussian": gs.Gaussian, "exponential": gs.Exponential,
          "spherical": gs.Spherical, "matern": gs.Matern}
JITTER = 1e-8
"""Added to the diagonal before a Cholesky factorisation (a nugget of 1e-8)."""


def covariance_model(variogram: Variogram, azimuth: float) -> gs.CovModel:
    """The gstools model (3-D, variance 1) of ``variogram`` with its major axis at
    ``azimuth`` degrees clockwise from y (see the module's docstring)."""
    major, minor, vertical = variogram.ranges
    kwargs = {"nu": variogram.nu} if variogram.model == "matern" else {}
    scale = practical_range(variogram.model, variogram.nu)
    return MODELS[variogram.model](dim=3, var=1.0, len_scale=major / scale,
                                   anis=[minor / major, vertical / major],
                                   angles=[math.radians(90.0 - azimuth), 0.0, 0.0], **kwargs)


@functools.lru_cache(maxsize=64)
def practical_range(model: str, nu: float = 1.5) -> float:
    """Where ``model`` with length scale 1 has correlation :data:`PRACTICAL_CORRELATION`
    (1 for the spherical model, whose correlation reaches 0 there)."""
    if model == "spherical":
        return 1.0
    kwargs = {"nu": nu} if model == "matern" else {}
    m = MODELS[model](dim=3, var=1.0, len_scale=1.0, **kwargs)
    return float(brentq(lambda h: m.correlation(h) - PRACTICAL_CORRELATION, 1e-6, 1e3))


def correlation_root(model: gs.CovModel, pos: np.ndarray) -> np.ndarray:
    """``R`` ``(n, n)`` with ``R R^T`` the correlation matrix of the points ``pos`` ``(3, n)``
    under ``model`` (anisotropy and rotation applied by gstools' ``isometrize``), so that
    ``R @ e`` with ``e ~ N(0, I)`` is an exact draw. Cholesky with :data:`JITTER` on the
    diagonal; a matrix it refuses (a Gaussian model's is nearly singular) gets the symmetric
    root of its eigen-decomposition, rounding's negative eigenvalues set to 0."""
    iso = model.isometrize(pos)
    corr = model.correlation(cdist(iso.T, iso.T))
    try:
        return cholesky(corr + JITTER * np.eye(corr.shape[0]), lower=True, check_finite=False)
    except LinAlgError:
        w, v = np.linalg.eigh(corr)
        return v * np.sqrt(np.clip(w, 0.0, None))
