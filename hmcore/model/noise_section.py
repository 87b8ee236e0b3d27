"""The case file's ``[noise]`` section: the measurement error the user states, per quantity and
optionally per well, in ERT's terms::

    [noise.WBHP]
    absolute = 2.0                 # ERT's ABS: sigma = 2 bar on every row
    correlation_days = 60          # time correlation length (AR(1): rho = exp(-spacing / 60))

    [noise.WGOR]
    relative = 0.05                # ERT's REL: sigma = 5 % of the observed value ...
    relative_min = 2.0             # ... and never below 2 (RELMIN)

    [noise.WBHP.wells.PRO-1]       # one well's own statement (quote names with odd characters)
    absolute = 1.0

Rows with a ``sigma`` in the observed history keep it; rows of a stated quantity (and well)
take the stated level; the rest are estimated from the data
(:class:`hmcore.scoring.observations.ObservationSet`). A zero or negative error is refused, as
ERT refuses a zero error: it would make a row exact (infinite weight). A relative error on a
row whose value is 0 would be zero too, so such a statement needs ``relative_min``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator, model_validator

from hmcore.errors import Problem
from hmcore.model.validation import did_you_mean

NOISE_QUANTITIES = ("WBHP", "WOPR", "WWPR", "WGPR", "WGOR", "WWCT")
"""Quantities whose noise weighs a fit (:data:`hmcore.scoring.noise.RESPONSE_OF`)."""


MAX_STATED_RHO = 0.99
"""Largest AR(1) correlation a stated correlation length may give (0.99: the whitening stays
well conditioned)."""


class NoiseLevel(BaseModel):
    """One statement of measurement error: ``absolute`` (ABS), or ``relative`` of the observed
    value (REL), with ``relative_min`` as its least value (RELMIN); ``correlation_days`` the
    time correlation length (0: white noise). Every key is optional: a statement with only
    ``correlation_days`` states the correlation and leaves the level to the estimate."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)

    absolute: float | None = None
    relative: float | None = None
    relative_min: float | None = None
    correlation_days: float | None = None

    @field_validator("absolute", "relative", "relative_min")
    @classmethod
    def _positive(cls, value: float | None) -> float | None:
        if value is not None and not value > 0:
            raise ValueError(f"a measurement error must be > 0, got {value:g}: a zero error "
                             "would make its rows exact (ERT refuses it too); give the "
                             "gauge's error, or remove the key to estimate it from the data")
        return value

    @field_validator("correlation_days")
    @classmethod
    def _not_negative(cls, value: float | None) -> float | None:
        if value is not None and value < 0:
            raise ValueError(f"correlation_days must be >= 0 (0: white noise), got {value:g}")
        return value

    @model_validator(mode="after")
    def _one_mode(self) -> NoiseLevel:
        if self.absolute is not None and self.relative is not None:
            raise ValueError("give either absolute (ERT's ABS) or relative (REL, with "
                             "relative_min: RELMIN), not both")
        if self.relative_min is not None and self.relative is None:
            raise ValueError("relative_min is the least value of a relative error: give "
                             "relative too, or use absolute")
        return self

    @property
    def mode(self) -> str | None:
        """ERT's name of the error mode ('ABS', 'REL', 'RELMIN'), None when no level is stated."""
        if self.absolute is not None:
            return "ABS"
        if self.relative is not None:
            return "RELMIN" if self.relative_min is not None else "REL"
        return None

    def sigma(self, values: np.ndarray) -> np.ndarray | None:
        """The stated error of rows with observed ``values`` (None: no level stated); a REL
        error of a zero value is 0, which the caller must not use."""
        v = np.abs(np.asarray(values, float))
        if self.absolute is not None:
            return np.full(v.shape, self.absolute)
        if self.relative is not None:
            return np.maximum(self.relative * v, self.relative_min or 0.0)
        return None

    def rho(self, spacing_days: float) -> float | None:
        """AR(1) correlation between rows ``spacing_days`` apart: ``exp(-spacing / length)``
        (None: no length stated; 0 for white noise)."""
        if self.correlation_days is None:
            return None
        if self.correlation_days == 0 or not spacing_days > 0:
            return 0.0
        return min(math.exp(-spacing_days / self.correlation_days), MAX_STATED_RHO)

    def over(self, base: NoiseLevel) -> NoiseLevel:
        """This statement where it states something, ``base`` elsewhere: the level as a whole
        (a well's ``relative`` replaces the quantity's ``absolute``), the correlation apart."""
        level = self if self.mode is not None else base
        corr = self.correlation_days if self.correlation_days is not None \
            else base.correlation_days
        return NoiseLevel(absolute=level.absolute, relative=level.relative,
                          relative_min=level.relative_min, correlation_days=corr)


class QuantityNoise(NoiseLevel):
    """The statement for one quantity, with wells that state their own (``wells``)."""

    wells: dict[str, NoiseLevel] = {}

    def for_well(self, well: str) -> NoiseLevel:
        own = self.wells.get(well)
        return own.over(self) if own is not None else NoiseLevel(
            absolute=self.absolute, relative=self.relative, relative_min=self.relative_min,
            correlation_days=self.correlation_days)


NoiseSection = dict[str, QuantityNoise]
"""The ``[noise]`` section: quantity -> statement."""


def noise_name_problems(raw, where: str, wells: Iterable[str] | None) -> list[Problem]:
    """Unknown quantities and wells in the raw ``[noise]`` table (checked on the TOML data,
    so they are reported even when a value elsewhere is wrong). ``where`` names the file;
    ``wells`` are the deck's (None: not known, not checked)."""
    if not isinstance(raw, dict):
        return []  # the type error comes from the section's validation
    out = []
    known = sorted(wells) if wells is not None else None
    for q, stated in raw.items():
        if q not in NOISE_QUANTITIES:
            out.append(Problem(f"{where} key 'noise.{q}'", f"unknown quantity '{q}'"
                               + did_you_mean(q, NOISE_QUANTITIES),
                               f"the quantities with noise are {list(NOISE_QUANTITIES)}"))
            continue
        per_well = stated.get("wells") if isinstance(stated, dict) else None
        if known is None or not isinstance(per_well, dict):
            continue
        for w in per_well:
            if w not in known:
                out.append(Problem(f"{where} key 'noise.{q}.wells.{w}'", f"unknown well '{w}'"
                                   + did_you_mean(w, known), f"the deck's wells are {known}"))
    return out


def valid_statements(raw) -> NoiseSection:
    """The statements of the raw ``[noise]`` table that are valid by themselves (known
    quantity, valid values), so that the checks that need the observed history run in the same
    pass as the section's own validation."""
    out: NoiseSection = {}
    for q, stated in (raw.items() if isinstance(raw, dict) else ()):
        if q in NOISE_QUANTITIES:
            try:
                out[q] = QuantityNoise.model_validate(stated)
            except ValidationError:
                continue
    return out


def zero_error_problems(section: NoiseSection, where: str, observed: pd.DataFrame
                        ) -> list[Problem]:
    """A relative error without ``relative_min`` on fitted rows whose value is 0 (and that have
    no ``sigma`` of their own): their error would be 0. GOR and water cut rows count only while
    the well flows (shut-in ones are not fitted)."""
    found: dict[str, list[tuple[str, int, float]]] = {}
    rows = observed[~observed.derived.astype(bool)] if "derived" in observed else observed
    for q, stated in section.items():
        sub = rows[rows.quantity == q]
        if "sigma" in sub:
            sub = sub[sub.sigma.isna()]
        if q in ("WGOR", "WWCT") and "flowing" in sub:
            sub = sub[sub.flowing.astype(bool)]
        for well, g in sub.groupby("well", sort=True):
            level = stated.for_well(str(well))
            zero = g[g.value.abs() == 0]
            if level.mode != "REL" or zero.empty:
                continue
            key = f"noise.{q}.wells.{well}" if str(well) in stated.wells else f"noise.{q}"
            found.setdefault(key, []).append((str(well), len(zero), float(zero.days.iloc[0])))
    out = []
    for key, hits in found.items():
        q = key.split(".")[1]
        rel = section[q].for_well(hits[0][0]).relative
        wells = ", ".join(f"{w} ({n} row(s), first on day {d:g})" for w, n, d in hits)
        out.append(Problem(f"{where} key '{key}'", f"relative = {rel:g} gives {q} an error of "
                           f"0 on rows whose value is 0: {wells}",
                           "add relative_min (ERT's RELMIN: the least error), or give absolute"))
    return out
