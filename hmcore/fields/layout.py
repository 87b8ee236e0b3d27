"""Where each parameter sits in a row of the smoother's ensemble matrix.

The smoother updates one matrix ``X`` ``(members, parameters)``; a case's fields and scalar
parameters are laid out in it side by side: every field's active cells (``n_active``
columns each, in the grid's active order), in the order given, then one column per scalar
(in its own update space, e.g. the scaled coordinate of a skin). :class:`Layout` stacks the
per-field arrays into ``X``, splits ``X`` back, and gives the parameters' locations for
distance localisation (a cell's centre; NaN for a scalar, which is not localised).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hmcore.fields.grid import FieldGrid


@dataclass(frozen=True)
class Layout:
    """``fields`` (names, ``n_active`` columns each) then ``scalars`` (one column each)."""

    fields: tuple[str, ...]
    scalars: tuple[str, ...]
    n_active: int

    @property
    def size(self) -> int:
        """Columns of ``X``."""
        return len(self.fields) * self.n_active + len(self.scalars)

    def columns(self, name: str) -> slice:
        """The columns of parameter ``name``; KeyError naming the parameters otherwise."""
        if name in self.fields:
            k = self.fields.index(name)
            return slice(k * self.n_active, (k + 1) * self.n_active)
        if name in self.scalars:
            k = len(self.fields) * self.n_active + self.scalars.index(name)
            return slice(k, k + 1)
        raise KeyError(f"no parameter {name!r}; the layout has {[*self.fields, *self.scalars]}")

    def stack(self, fields: Mapping[str, np.ndarray],
              scalars: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """``X`` ``(members, size)`` float32 from ``fields[name]`` ``(members, n_active)`` and
        ``scalars[name]`` ``(members,)``."""
        scalars = scalars or {}
        parts = [np.asarray(fields[n], np.float32) for n in self.fields]
        parts += [np.asarray(scalars[n], np.float32)[:, None] for n in self.scalars]
        members = {p.shape[0] for p in parts}
        if len(members) != 1 or any(p.shape[1] != self.n_active for p in parts[:len(self.fields)]):
            raise ValueError(f"every field must be (members, {self.n_active}) and every scalar "
                             f"(members,), with one number of members; got "
                             f"{[p.shape for p in parts]}")
        return np.concatenate(parts, axis=1)

    def split(self, X: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """``X`` ``(members, size)`` -> ({field: (members, n_active)}, {scalar: (members,)}),
        views into ``X``."""
        if X.ndim != 2 or X.shape[1] != self.size:
            raise ValueError(f"X must have shape (members, {self.size}), got {X.shape}")
        return ({n: X[:, self.columns(n)] for n in self.fields},
                {n: X[:, self.columns(n)][:, 0] for n in self.scalars})

    def locations(self, grid: FieldGrid) -> np.ndarray:
        """x, y of every column ``(size, 2)``: the cells' centres for each field, NaN for the
        scalars."""
        if grid.n_active != self.n_active:
            raise ValueError(f"the grid has {grid.n_active} active cells, the layout "
                             f"{self.n_active}")
        cells = np.tile(grid.centres[:, :2], (len(self.fields), 1))
        return np.vstack([cells, np.full((len(self.scalars), 2), np.nan)])
