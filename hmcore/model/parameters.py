"""Parameters as declared data: name, kind, bounds and what they touch in the deck.

The action space of every proposer is ``[-1, 1]^n``; :class:`Scaling` is the one mapping of
scaled coordinates to physical values and back (linear in the value, or in its logarithm for a
parameter with ``log = true``), and :class:`ParameterSpace` maps a case's actions with it.

Kinds (each turns a value into deck edits, see :mod:`hmcore.model.run_deck`):

* ``multiply`` - multiply grid keywords (``PORO``, ``PERMX``, ...), optionally in a 1-based box
  ``(i1, i2, j1, j2, k1, k2)`` or in the cells of ``region_numbers`` of the region keyword
  ``region`` (``MULTNUM``, ``FLUXNUM`` or ``OPERNUM`` as the GRID section defines it; written
  as ``MULTIREG``); several keywords may share one factor.
* ``multregt`` - the transmissibility multiplier between two regions (``MULTREGT``):
  ``region_numbers = [r1, r2]`` of ``region`` (default ``MULTNUM``), all directions.
* ``skin`` - set COMPDAT item 11 (skin) on the connections of ``wells`` (all producers when
  empty), optionally only on ``layers`` (1-based k).
* ``item_multiply`` - multiply numeric item ``item`` (1-based) of the records of ``keywords[0]``
  (e.g. AQUCT item 4, the aquifer permeability; AQUFETP item 4, its volume), only in records
  whose first item equals ``match`` when given (an aquifer id, say).
* ``relperm`` - transform column ``item`` (1-based, default 2: krw in SWOF/SWFN, krg in
  SGOF/SGFN) of every table of ``keywords[0]``: ``mode="scale"`` multiplies it (capped at 1),
  ``mode="power"`` raises its normalised shape to the given exponent, keeping end points;
  ``mode="endpoint"`` moves the critical saturation of that curve (where it reaches 0: SWCR
  for krw in SWOF/SWFN, SOWCR for krow, SGCR for krg) by the value, in saturation units,
  stretching the curve between it and its far end point (two-point end-point scaling, applied
  to the table itself; the value may be negative).
* ``table_multiply`` - multiply column ``item`` (1-based) of every row of every table of
  ``keywords[0]``, a fluid table (:data:`TABLE_MULTIPLIABLE`): the initial solution gas-oil
  ratio versus depth (``RSVD`` item 2), the bubble point (``PBVD``), a dry gas's or a dead
  oil's formation volume factor or viscosity (``PVDG`` / ``PVDO`` items 2 / 3).
* ``wpimult`` - multiply the productivity index of ``wells``' connections (all producers when
  empty) with ``WPIMULT``, written after every COMPDAT that connects them; with ``start_day``
  only from the first report step at or after that day (a productivity change during the
  history: the WPIMULT is written in the schedule at that step, and after the COMPDATs that
  follow it).
* ``fault`` - set the transmissibility multiplier (``MULTFLT``) of the faults named in
  ``faults`` (the deck's ``FAULTS`` names), replacing the deck's own multiplier.
* ``latent`` - hmflow's own, never a case file's: the coefficient of one mode of the fields'
  prior ensemble (:mod:`hmcore.fields.latent`, a case's ``[latent]`` section). It edits no deck
  text; the run writes the fields the coefficients make
  (:class:`hmcore.fields.members.LatentSimulator`).
* ``trend`` - hmflow's own, never a case file's (a hidden truth's edit,
  :mod:`hmcore.scenarios.generators`): multiply grid keywords by a factor that varies
  log-linearly across the grid along the horizontal ``direction`` (degrees from +i towards +j):
  x1/value at the grid's farthest column behind, x value at the farthest ahead
  (:func:`hmcore.model.run_deck.trend_factors`, one ``MULTIPLY`` record per column).
* ``recomplete`` - hmflow's own too: the one well of ``wells`` recompleted from ``start_day``
  on, its connections so far shut and new ones opened in ``layers`` (a workover; a COMPDAT in the
  schedule at that report step), the new connections' productivity index multiplied by the
  value (``WPIMULT``; 1: as the deck's own connection factors compute it).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated, Literal

import numpy as np
from pydantic import AllowInfNan, BaseModel, ConfigDict, Field, Strict, model_validator

from hmcore.eclipse.tables import TableFamily, editable


class ParameterKind(StrEnum):
    """What a parameter does to the deck (see the module's docstring)."""

    MULTIPLY = "multiply"
    SKIN = "skin"
    ITEM_MULTIPLY = "item_multiply"
    RELPERM = "relperm"
    FAULT = "fault"
    MULTREGT = "multregt"
    WPIMULT = "wpimult"
    TABLE_MULTIPLY = "table_multiply"
    LATENT = "latent"
    TREND = "trend"
    RECOMPLETE = "recomplete"


Bound = Annotated[float, Strict(), AllowInfNan(False)]  # a finite number (TOML true/inf refused)
MULTIREG_REGIONS = {"MULTNUM": "M", "FLUXNUM": "F", "OPERNUM": "O"}
RELPERM_COLUMNS = editable(TableFamily.RELPERM)  # table -> 1-based relative permeability
# columns (column 1 is the saturation, the last of SWOF/SGOF/SLGOF/SWFN/SGFN capillary pressure)
RELPERM_TABLES = tuple(RELPERM_COLUMNS)
TABLE_MULTIPLIABLE = editable(TableFamily.FLUID)  # table -> 1-based columns a table_multiply
# may scale (column 1 is the depth or the pressure the table is read at)
GRID_MULTIPLIABLE = ("PORO", "PERMX", "PERMY", "PERMZ", "NTG", "MULTX", "MULTY", "MULTZ",
                     "MULTX-", "MULTY-", "MULTZ-")


class Parameter(BaseModel):
    """One calibration parameter. Bounds are in physical units."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1)
    kind: ParameterKind
    low: Bound
    high: Bound
    keywords: tuple[str, ...] = ()
    wells: tuple[str, ...] = ()
    faults: tuple[str, ...] = ()
    layers: tuple[int, ...] = ()
    box: tuple[int, int, int, int, int, int] | None = None
    region: str | None = None
    region_numbers: tuple[int, ...] = ()
    item: int | None = Field(default=None, ge=1)
    match: str | None = None
    mode: Literal["scale", "power", "endpoint"] = "scale"
    start_day: Bound | None = Field(default=None, gt=0)
    direction: Bound | None = Field(default=None, exclude_if=lambda d: d is None)
    """A ``trend``'s horizontal direction of increase, degrees from +i towards +j. Left out of a
    dump when None, so that every other parameter is written as before."""
    log: bool = Field(default=False, exclude_if=lambda log: not log)
    """Scaled linearly in log(value) (a factor: equal steps are equal ratios), not in the
    value. Left out of a dump when False, so that a parameter without it is written as
    before."""
    description: str = ""

    @model_validator(mode="after")
    def _check(self) -> "Parameter":
        if not self.low < self.high:
            raise ValueError(f"low < high must hold for parameter '{self.name}', "
                             f"got low={self.low}, high={self.high}")
        if self.kind in ("multiply", "trend"):
            if not self.keywords:
                raise ValueError(f"parameter '{self.name}' of kind '{self.kind}' needs keywords, "
                                 f"e.g. keywords = [\"PERMX\"]")
            bad = [k for k in self.keywords if k.upper() not in GRID_MULTIPLIABLE]
            if bad:
                raise ValueError(f"parameter '{self.name}': cannot multiply {bad}; "
                                 f"allowed keywords are {list(GRID_MULTIPLIABLE)}")
            if self.low <= 0:
                raise ValueError(f"multiplier '{self.name}' must have low > 0, got low={self.low}")
        if self.kind in ("item_multiply", "relperm", "table_multiply") and len(self.keywords) != 1:
            raise ValueError(f"parameter '{self.name}' of kind '{self.kind}' needs exactly one "
                             f"keyword, got {list(self.keywords)}")
        if self.kind == "item_multiply" and self.item is None:
            raise ValueError(f"parameter '{self.name}' of kind 'item_multiply' needs item "
                             "(the 1-based record item to multiply)")
        if self.kind == "relperm" and self.keywords[0].upper() not in RELPERM_TABLES:
            raise ValueError(f"parameter '{self.name}': relperm tables are {list(RELPERM_TABLES)}, "
                             f"got {self.keywords[0]!r}")
        if self.kind == "relperm" and (self.item or 2) not in \
                RELPERM_COLUMNS[self.keywords[0].upper()]:
            columns = RELPERM_COLUMNS[self.keywords[0].upper()]
            raise ValueError(f"parameter '{self.name}': item {self.item} of "
                             f"{self.keywords[0].upper()} is not a relative permeability column; "
                             f"use item = {' or '.join(map(str, columns))} (column 1 is the "
                             "saturation, the others capillary pressure)")
        if self.kind == "table_multiply" and self.keywords[0].upper() not in TABLE_MULTIPLIABLE:
            raise ValueError(f"parameter '{self.name}': table_multiply tables are "
                             f"{list(TABLE_MULTIPLIABLE)}, got {self.keywords[0]!r}")
        if self.kind == "table_multiply" and self.item not in \
                TABLE_MULTIPLIABLE[self.keywords[0].upper()]:
            columns = TABLE_MULTIPLIABLE[self.keywords[0].upper()]
            raise ValueError(f"parameter '{self.name}': table_multiply needs item = "
                             f"{' or '.join(map(str, columns))} for {self.keywords[0].upper()} "
                             f"(the column to multiply), got item = {self.item}")
        if self.region is not None and self.region.upper() not in MULTIREG_REGIONS:
            raise ValueError(f"parameter '{self.name}': region must be one of "
                             f"{list(MULTIREG_REGIONS)} (what MULTIREG and MULTREGT read), got "
                             f"{self.region!r}; to use FIPNUM's layout, copy it into MULTNUM "
                             "in the GRID section")
        if self.region is not None and self.kind == "multiply" and not self.region_numbers:
            raise ValueError(f"parameter '{self.name}': region needs region_numbers, "
                             "e.g. region_numbers = [2]")
        if self.region is not None and self.box is not None:
            raise ValueError(f"parameter '{self.name}': give a box or a region, not both")
        if self.region_numbers and self.region is None and self.kind != "multregt":
            raise ValueError(f"parameter '{self.name}': region_numbers need region, "
                             "e.g. region = \"MULTNUM\"")
        if self.kind == "multregt" and (len(self.region_numbers) != 2
                                        or len(set(self.region_numbers)) != 2):
            raise ValueError(f"parameter '{self.name}' of kind 'multregt' needs two different "
                             f"region_numbers [r1, r2], got {list(self.region_numbers)}")
        if self.kind == "multregt" and self.low < 0:
            raise ValueError(f"parameter '{self.name}' must have low >= 0, got low={self.low}")
        if self.kind == "fault" and not self.faults:
            raise ValueError(f"parameter '{self.name}' of kind 'fault' needs faults, "
                             "e.g. faults = [\"F1\"] (names from the deck's FAULTS keyword)")
        if self.kind == "fault" and self.low < 0:
            raise ValueError(f"fault multiplier '{self.name}' must have low >= 0, "
                             f"got low={self.low}")
        if self.kind == "relperm" and self.mode == "endpoint" and not (
                -0.5 < self.low and self.high < 0.5):
            raise ValueError(f"parameter '{self.name}': an end-point shift is a saturation "
                             f"change within (-0.5, 0.5), got [{self.low}, {self.high}]")
        if (self.kind in ("item_multiply", "wpimult", "table_multiply")
                or (self.kind == "relperm" and self.mode != "endpoint")) and self.low <= 0:
            raise ValueError(f"parameter '{self.name}' must have low > 0, got low={self.low}")
        if self.mode != "scale" and self.kind != "relperm":
            raise ValueError(f"parameter '{self.name}': mode = {self.mode!r} is only for kind "
                             f"'relperm' (how a relative permeability curve changes), not "
                             f"'{self.kind}'; remove it")
        if self.log and self.low <= 0:
            raise ValueError(f"parameter '{self.name}': a log scale needs low > 0, "
                             f"got low={self.low}")
        if self.start_day is not None and self.kind not in ("wpimult", "recomplete"):
            raise ValueError(f"parameter '{self.name}': start_day (an edit from a date on) is "
                             f"only for kind 'wpimult' (or hmflow's 'recomplete'), not "
                             f"'{self.kind}'")
        if (self.direction is None) != (self.kind != "trend") or (
                self.kind == "trend" and (self.box is not None or self.region is not None)):
            raise ValueError(f"parameter '{self.name}': a direction is for kind 'trend' only, "
                             "and a trend needs one (it spans the whole grid: no box or region)")
        if self.kind == "recomplete" and (len(self.wells) != 1 or not self.layers
                                          or self.start_day is None or self.low <= 0):
            raise ValueError(f"parameter '{self.name}' of kind 'recomplete' needs one well, the "
                             "layers it is recompleted in, a start_day and low > 0")
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


@dataclass(frozen=True)
class Scaling:
    """Physical values <-> scaled coordinates in [-1, 1], per parameter: ``low`` maps to -1 and
    ``high`` to 1, linearly in the value, or in log(value) where ``log`` is set."""

    lo: np.ndarray
    """Where -1 maps to: ``low``, or log(low) where ``log``."""
    hi: np.ndarray
    """Where 1 maps to: ``high``, or log(high) where ``log``."""
    log: np.ndarray
    """Which parameters are scaled in log(value) (bool)."""

    @classmethod
    def of(cls, parameters: tuple[Parameter, ...] | list[Parameter]) -> Scaling:
        """The scaling of ``parameters``, each by its own ``log`` flag."""
        log = np.array([p.log for p in parameters], dtype=bool)
        lo = np.array([p.low for p in parameters], dtype=float)
        hi = np.array([p.high for p in parameters], dtype=float)
        lo[log] = np.log(lo[log])
        hi[log] = np.log(hi[log])
        return cls(lo, hi, log)

    def to_values(self, u: np.ndarray) -> np.ndarray:
        """Scaled coordinates (clipped to [-1, 1]) -> physical values."""
        u = np.clip(np.asarray(u, float), -1.0, 1.0)
        x = self.lo + (u + 1.0) * 0.5 * (self.hi - self.lo)
        x[self.log] = np.exp(x[self.log])
        return x

    def to_scaled(self, values: np.ndarray) -> np.ndarray:
        """Physical values -> scaled coordinates (not clipped)."""
        t = np.array(values, dtype=float)
        t[self.log] = np.log(np.maximum(t[self.log], 1e-300))
        return 2.0 * (t - self.lo) / (self.hi - self.lo) - 1.0


class ParameterSpace(BaseModel):
    """An ordered set of parameters; maps actions in [-1, 1]^n to physical values and back.

    Empty (``dim == 0``) for a case of field parameters only (:mod:`hmcore.model.case_fields`):
    its runs keep the deck's own values. A calibration method needs ``dim >= 1``, which the
    command line checks before anything runs (``flows.inputs.scalar_problems``)."""

    model_config = ConfigDict(frozen=True)

    parameters: tuple[Parameter, ...]

    @model_validator(mode="after")
    def _unique(self) -> "ParameterSpace":
        names = [p.name for p in self.parameters]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"parameter names must be unique, got duplicates {dup}")
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

    @property
    def scaling(self) -> Scaling:
        return Scaling.of(self.parameters)

    def to_values(self, action: np.ndarray) -> dict[str, float]:
        """Action in [-1, 1]^n (clipped) -> {name: physical value}."""
        x = self.scaling.to_values(np.asarray(action, dtype=float).reshape(self.dim))
        return {n: float(v) for n, v in zip(self.names, x)}

    def to_action(self, values: dict[str, float]) -> np.ndarray:
        """{name: physical value} -> action in [-1, 1]^n (not clipped)."""
        missing = [n for n in self.names if n not in values]
        if missing:
            raise KeyError(f"values are missing parameters {missing}")
        return self.scaling.to_scaled([float(values[n]) for n in self.names])

    def check_in_bounds(self, values: dict[str, float]) -> list[str]:
        """Messages for values outside their bounds (empty when all are inside)."""
        msgs = []
        for p in self.parameters:
            v = values.get(p.name)
            if v is not None and not (p.low <= v <= p.high):
                msgs.append(f"{p.name}={v} is outside [{p.low}, {p.high}]")
        return msgs

