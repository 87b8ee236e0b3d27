"""A field's values between its update space and the deck's physical values.

The smoother works on ``u``: log10 of the value for a field with ``in_log`` (permeability by
default, so that a multiplicative error is additive), the value otherwise. What the simulator
gets is the physical value, truncated to the field's bounds (ERT's FIELD ``OUTPUT_TRANSFORM``
and ``MIN``/``MAX``). Arrays keep their shape: one value per active cell, ``(n_active,)``, or
a whole ensemble, ``(members, n_active)``.
"""

from __future__ import annotations

import numpy as np

from hmcore.fields.spec import FieldSpec


def to_physical(u: np.ndarray, field: FieldSpec) -> np.ndarray:
    """Update-space values -> physical values in ``field.bounds`` (float64, same shape).

    Non-finite values raise ValueError: a member left out of an update (NaN) has no field to
    write."""
    u = np.asarray(u, dtype=np.float64)
    if not np.isfinite(u).all():
        raise ValueError(f"field '{field.name}': {int((~np.isfinite(u)).sum())} value(s) are "
                         "not finite (a member left out of the update has no field to write)")
    low, high = field.bounds
    with np.errstate(over="ignore"):  # 10**400 is inf, then truncated to high
        values = np.power(10.0, u) if field.in_log else u.copy()
    return np.clip(values, low, high)


def to_update_space(values: np.ndarray, field: FieldSpec) -> np.ndarray:
    """Physical values -> update space (float32, same shape); ValueError when a log field has
    a value <= 0 (its log does not exist)."""
    values = np.asarray(values, dtype=np.float64)
    if field.in_log:
        bad = ~(values > 0)
        if bad.any():
            raise ValueError(f"field '{field.name}' ({field.keyword}) is updated in log space "
                             f"and needs values > 0; {int(bad.sum())} value(s) are not, "
                             f"e.g. {float(values[bad].flat[0])}")
        values = np.log10(values)
    return values.astype(np.float32)
