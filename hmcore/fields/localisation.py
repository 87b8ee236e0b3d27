"""Distance-based localisation of the ensemble smoother: how much a datum may move a cell.

The Kalman gain ``K`` ``(parameters, observations)`` of an ensemble smoother is computed from
a finite ensemble, so a datum seems to inform cells far from its well by chance correlation
(spurious correlation), and the ensemble's spread collapses there. Distance localisation
multiplies ``K`` element by element by a taper ``rho`` that is 1 at the datum's well and falls
to 0 at ``radius`` (Emerick 2016, *J. Pet. Sci. Eng.* 139, doi:10.1016/j.petrol.2016.01.029;
the taper is Gaspari & Cohn 1999's fifth-order piecewise rational function, eq. 4.10, with
half-width ``c = radius / 2``). Distances are horizontal, between a cell's centre and the
datum's location (its well's connected cells' mean centre, say), in the deck's length unit.
A parameter without a location (a scalar: a skin, a fault multiplier) and a datum without one
(a field rate) are not localised: their taper is 1.
"""

from __future__ import annotations

import numpy as np


def gaspari_cohn(r: np.ndarray) -> np.ndarray:
    """Gaspari-Cohn's compactly supported correlation of ``r = distance / c`` (any shape):
    1 at 0, 0 from ``r = 2`` on, smooth in between."""
    r = np.abs(np.asarray(r, dtype=np.float64))
    out = np.zeros_like(r)
    near = r <= 1.0
    far = (r > 1.0) & (r < 2.0)
    x = r[near]
    out[near] = -0.25 * x**5 + 0.5 * x**4 + 0.625 * x**3 - 5.0 / 3.0 * x**2 + 1.0
    x = r[far]
    out[far] = (x**5 / 12.0 - 0.5 * x**4 + 0.625 * x**3 + 5.0 / 3.0 * x**2 - 5.0 * x + 4.0
                - 2.0 / (3.0 * x))
    return np.clip(out, 0.0, 1.0)


def distance_taper(parameter_xy: np.ndarray, observation_xy: np.ndarray,
                   radius: float) -> np.ndarray:
    """The taper ``(parameters, observations)`` in [0, 1]: Gaspari-Cohn of the horizontal
    distance with support ``radius``. ``parameter_xy`` ``(parameters, 2)`` and
    ``observation_xy`` ``(observations, 2)``; a row with NaN (no location) gets 1 throughout."""
    p = np.asarray(parameter_xy, dtype=np.float64)
    o = np.asarray(observation_xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or o.ndim != 2 or o.shape[1] != 2:
        raise ValueError(f"locations must be (n, 2) arrays of x, y; got {p.shape} and {o.shape}")
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    d = np.hypot(p[:, None, 0] - o[None, :, 0], p[:, None, 1] - o[None, :, 1])
    rho = gaspari_cohn(d / (radius / 2.0))
    rho[~np.isfinite(d)] = 1.0
    return rho
