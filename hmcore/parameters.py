"""Parameters as declared data: name, kind, bounds and what they touch in the deck.

The action space of every proposer is ``[-1, 1]^n``; :class:`ParameterSpace` is the one place
that maps actions to physical values (linearly) and back.

Kinds (each turns a value into deck edits, see :mod:`hmcore.deck`):

* ``multiply`` - multiply grid keywords (``PORO``, ``PERMX``, ...), optionally in a 1-based box
  ``(i1, i2, j1, j2, k1, k2)``; several keywords may share one factor.
* ``skin`` - set COMPDAT item 11 (skin) on the connections of ``wells`` (all producers when
  empty), optionally only on ``layers`` (1-based k).
* ``item_multiply`` - multiply numeric item ``item`` (1-based) of the records of ``keywords[0]``
  (e.g. AQUCT item 4, the aquifer permeability; AQUFETP item 4, its volume), only in records
  whose first item equals ``match`` when given (an aquifer id, say).
* ``relperm`` - transform column ``item`` (1-based, default 2: krw in SWOF/SWFN, krg in
  SGOF/SGFN) of every table of ``keywords[0]``: ``mode="scale"`` multiplies it (capped at 1),
  ``mode="power"`` raises its normalised shape to the given exponent, keeping end points.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

ParameterKind = Literal["multiply", "skin", "item_multiply", "relperm"]
RELPERM_TABLES = ("SWOF", "SGOF", "SWFN", "SGFN", "SOF3", "SOF2", "SLGOF")
GRID_MULTIPLIABLE = ("PORO", "PERMX", "PERMY", "PERMZ", "NTG", "MULTX", "MULTY", "MULTZ",
                     "MULTX-", "MULTY-", "MULTZ-")


class Parameter(BaseModel):
    """One calibration parameter. Bounds are in physical units."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1)
    kind: ParameterKind
    low: float
    high: float
    keywords: tuple[str, ...] = ()
    wells: tuple[str, ...] = ()
    layers: tuple[int, ...] = ()
    box: tuple[int, int, int, int, int, int] | None = None
    item: int | None = Field(default=None, ge=1)
    match: str | None = None
    mode: Literal["scale", "power"] = "scale"
    description: str = ""

    @model_validator(mode="after")
    def _check(self) -> "Parameter":
        if not self.low < self.high:
            raise ValueError(f"low < high must hold for parameter '{self.name}', "
                             f"got low={self.low}, high={self.high}")
        if self.kind == "multiply":
            if not self.keywords:
                raise ValueError(f"parameter '{self.name}' of kind 'multiply' needs keywords, "
                                 f"e.g. keywords = [\"PERMX\"]")
            bad = [k for k in self.keywords if k.upper() not in GRID_MULTIPLIABLE]
            if bad:
                raise ValueError(f"parameter '{self.name}': cannot multiply {bad}; "
                                 f"allowed keywords are {list(GRID_MULTIPLIABLE)}")
            if self.low <= 0:
                raise ValueError(f"multiplier '{self.name}' must have low > 0, got low={self.low}")
        if self.kind in ("item_multiply", "relperm") and len(self.keywords) != 1:
            raise ValueError(f"parameter '{self.name}' of kind '{self.kind}' needs exactly one "
                             f"keyword, got {list(self.keywords)}")
        if self.kind == "item_multiply" and self.item is None:
            raise ValueError(f"parameter '{self.name}' of kind 'item_multiply' needs item "
                             "(the 1-based record item to multiply)")
        if self.kind == "relperm" and self.keywords[0].upper() not in RELPERM_TABLES:
            raise ValueError(f"parameter '{self.name}': relperm tables are {list(RELPERM_TABLES)}, "
                             f"got {self.keywords[0]!r}")
        if self.kind in ("item_multiply", "relperm") and self.low <= 0:
            raise ValueError(f"parameter '{self.name}' must have low > 0, got low={self.low}")
        if self.box is not None:
            i1, i2, j1, j2, k1, k2 = self.box
            if not (1 <= i1 <= i2 and 1 <= j1 <= j2 and 1 <= k1 <= k2):
                raise ValueError(f"parameter '{self.name}': box must be 1-based with "
                                 f"i1<=i2, j1<=j2, k1<=k2, got {self.box}")
        return self


def reference_parameters() -> tuple[Parameter, ...]:
    """The five global parameters of the reference method (PUNQ-S3 paper)."""
    return (
        Parameter(name="poro_mult", kind="multiply", keywords=("PORO",), low=0.8, high=1.2,
                  description="global porosity multiplier"),
        Parameter(name="permx_mult", kind="multiply", keywords=("PERMX",), low=0.3, high=3.0,
                  description="global permeability multiplier in I"),
        Parameter(name="permy_mult", kind="multiply", keywords=("PERMY",), low=0.3, high=3.0,
                  description="global permeability multiplier in J"),
        Parameter(name="permz_mult", kind="multiply", keywords=("PERMZ",), low=0.3, high=3.0,
                  description="global permeability multiplier in K"),
        Parameter(name="skin", kind="skin", low=-5.0, high=15.0,
                  description="skin factor on every producer connection"),
    )


class ParameterSpace(BaseModel):
    """An ordered set of parameters; maps actions in [-1, 1]^n to physical values and back."""

    model_config = ConfigDict(frozen=True)

    parameters: tuple[Parameter, ...]

    @model_validator(mode="after")
    def _unique(self) -> "ParameterSpace":
        names = [p.name for p in self.parameters]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"parameter names must be unique, got duplicates {dup}")
        if not names:
            raise ValueError("a parameter space needs at least one parameter")
        return self

    @classmethod
    def reference(cls) -> "ParameterSpace":
        return cls(parameters=reference_parameters())

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.parameters]

    @property
    def dim(self) -> int:
        return len(self.parameters)

    @property
    def low(self) -> np.ndarray:
        return np.array([p.low for p in self.parameters], dtype=float)

    @property
    def high(self) -> np.ndarray:
        return np.array([p.high for p in self.parameters], dtype=float)

    def to_values(self, action: np.ndarray) -> dict[str, float]:
        """Action in [-1, 1]^n (clipped) -> {name: physical value}."""
        a = np.clip(np.asarray(action, dtype=float).reshape(self.dim), -1.0, 1.0)
        x = self.low + (a + 1.0) * 0.5 * (self.high - self.low)
        return {n: float(v) for n, v in zip(self.names, x)}

    def to_action(self, values: dict[str, float]) -> np.ndarray:
        """{name: physical value} -> action in [-1, 1]^n (not clipped)."""
        missing = [n for n in self.names if n not in values]
        if missing:
            raise KeyError(f"values are missing parameters {missing}")
        x = np.array([float(values[n]) for n in self.names])
        return 2.0 * (x - self.low) / (self.high - self.low) - 1.0

    def check_in_bounds(self, values: dict[str, float]) -> list[str]:
        """Messages for values outside their bounds (empty when all are inside)."""
        msgs = []
        for p in self.parameters:
            v = values.get(p.name)
            if v is not None and not (p.low <= v <= p.high):
                msgs.append(f"{p.name}={v} is outside [{p.low}, {p.high}]")
        return msgs

