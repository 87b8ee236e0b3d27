"""A heterogeneous property field as a case file declares it: ``kind = "field"`` parameters and
their priors (validation models only; nothing here reads a deck). The ``[ensemble]`` section
is :mod:`hmcore.fields.ensemble`'s, the checks of a case's fields together
:mod:`hmcore.fields.fieldset`'s.

A field parameter is one value per active cell of one GRID keyword (:data:`FIELD_KEYWORDS`),
updated by the ensemble smoother in its *update space*: log10 of the value when ``log`` is set
(the default for permeability, whose relations are stated in log10 mD), the value itself
otherwise. ``low``/``high`` are physical bounds, applied by truncation when a member is written
(:mod:`hmcore.fields.transform`); the ensemble itself is never truncated (ERT's FIELD
``MIN``/``MAX`` do the same). ``copies`` names keywords that get the same values (PERMY equal
to PERMX, as a deck's ``COPY`` would).

The prior (``prior.source``) is one of

* ``"geostatistical"``: Gaussian random fields drawn by hmflow with gstools, one per zone
  (a range of layers, or the cells of one region number), each zone with its mean and standard
  deviation in update space and a variogram (model, ranges, azimuth);
* ``"relation"``: ``u = intercept + slope * u_src + e`` with ``u_src`` another field's values
  in its update space (``log10(k) = 0.77 + 9.02 * phi`` for PUNQ-S3, Floris et al. 2001) and
  ``e`` a residual field of standard deviation ``scatter`` with the source's variograms;
* ``"cosimulation"``: the target's zones' mean and std, its normal score correlated with the
  source's by ``correlation`` (``z = rho z_src + sqrt(1 - rho^2) z_new``);
* ``"files"``: the user's own realisations, one GRDECL file per member (ERT's way).

Errors state the broken rule with the values; the case loader adds the file and the key.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import (
    AllowInfNan,
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    field_validator,
    model_validator,
)

FIELD_KEYWORDS = ("PORO", "PERMX", "PERMY", "PERMZ", "NTG")
"""The GRID keywords a field parameter may replace."""
PERMEABILITY = ("PERMX", "PERMY", "PERMZ")
FRACTIONS = ("PORO", "NTG")
DEFAULT_BOUNDS = {"PORO": (1e-3, 1.0), "NTG": (1e-3, 1.0), "PERMX": (1e-3, 1e5),
                  "PERMY": (1e-3, 1e5), "PERMZ": (1e-3, 1e5)}
"""Physical truncation bounds when the case gives none (permeability in the deck's unit, mD).
Porosity and net-to-gross stay above 0: a cell without pore volume would be made inactive by
the simulator, and the members' grids would differ."""

Number = Annotated[float, Strict(), AllowInfNan(False)]  # a finite number; TOML true refused
Count = Annotated[int, Strict()]  # an integer; TOML 2.0 and true refused


class Section(BaseModel):
    """No unknown key, frozen, finite numbers (a case file's section)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False,
                              populate_by_name=True)


class Variogram(Section):
    """A stationary covariance model of a zone's normal score (variance 1).

    ``ranges`` = (major, minor, vertical) in the deck's length unit: the practical range, where
    the correlation falls to 5 % (the spherical model's range, where it reaches 0). ``azimuth``
    is the major axis in degrees clockwise from the grid's y axis (north); a pair [lo, hi]
    draws it uniformly per member (an uncertain paleocurrent, PUNQ-S3's 110-170 degrees).
    ``nu`` is the Matern smoothness."""

    model: Literal["gaussian", "exponential", "spherical", "matern"] = "spherical"
    ranges: tuple[Number, Number, Number]
    azimuth: Number | tuple[Number, Number] = 0.0
    nu: Number = 1.5

    @model_validator(mode="after")
    def _check(self) -> Variogram:
        major, minor, vertical = self.ranges
        if not (major > 0 and minor > 0 and vertical > 0):
            raise ValueError(f"variogram ranges (major, minor, vertical) must all be > 0, got "
                             f"{list(self.ranges)}")
        if minor > major:
            raise ValueError(f"variogram ranges must have major >= minor, got major={major}, "
                             f"minor={minor}")
        low, high = self.azimuth_range
        if not (-360.0 <= low <= high <= 360.0):
            raise ValueError(f"azimuth must be degrees in [-360, 360] with lo <= hi, got "
                             f"{self.azimuth!r}")
        if not self.nu > 0:
            raise ValueError(f"the Matern smoothness nu must be > 0, got nu={self.nu}")
        return self

    @property
    def azimuth_range(self) -> tuple[float, float]:
        """(lo, hi) in degrees; lo == hi for a fixed azimuth."""
        a = self.azimuth
        return (float(a), float(a)) if isinstance(a, (int, float)) else (float(a[0]), float(a[1]))


class Zone(Section):
    """Cells sharing one mean, standard deviation and variogram: the layers k1..k2 (1-based,
    inclusive) or the cells whose ``region`` keyword (e.g. FIPNUM) equals ``number``. ``mean``
    and ``std`` are in update space (log10 mD for a log permeability)."""

    layers: tuple[Count, Count] | None = None
    region: str | None = None
    number: Count | None = None
    mean: Number
    std: Number = Field(ge=0)
    variogram: Variogram | None = None

    @model_validator(mode="after")
    def _check(self) -> Zone:
        if (self.layers is None) == (self.region is None):
            raise ValueError("a zone needs either layers = [k1, k2] or region (with number), "
                             f"not both nor neither; got layers={self.layers}, "
                             f"region={self.region!r}")
        if self.layers is not None:
            k1, k2 = self.layers
            if not 1 <= k1 <= k2:
                raise ValueError(f"zone layers [k1, k2] must be 1-based with k1 <= k2, got "
                                 f"[{k1}, {k2}]")
        if self.region is not None and self.number is None:
            raise ValueError(f"a zone of region {self.region!r} needs number (the region "
                             "number of its cells)")
        if self.region is None and self.number is not None:
            raise ValueError(f"number = {self.number} needs region (the region keyword)")
        return self

    def label(self) -> str:
        """'layers 1-2' or 'FIPNUM 3', for messages."""
        if self.layers is not None:
            return f"layers {self.layers[0]}-{self.layers[1]}"
        return f"{self.region} {self.number}"


class GeostatisticalPrior(Section):
    """Gaussian random fields per zone (gstools); ``variogram`` is the zones' default."""

    source: Literal["geostatistical"]
    zones: tuple[Zone, ...] = Field(min_length=1)
    variogram: Variogram | None = None
    seed: Count = Field(ge=0)

    @model_validator(mode="after")
    def _check(self) -> GeostatisticalPrior:
        missing = [z.label() for z in self.zones if z.variogram is None]
        if missing and self.variogram is None:
            raise ValueError(f"zones {missing} have no variogram and the prior gives no default "
                             "one; add prior.variogram or a variogram to each zone")
        return self

    def variogram_of(self, zone: Zone) -> Variogram:
        return zone.variogram or self.variogram  # type: ignore[return-value]


class RelationPrior(Section):
    """``u = intercept + slope * u_src + e`` in update spaces, ``e`` of std ``scatter`` with the
    source's zones' variograms (``scatter = 0``: the relation exactly)."""

    source: Literal["relation"]
    from_: str = Field(alias="from", min_length=1)
    intercept: Number = 0.0
    slope: Number = 1.0
    scatter: Number = Field(default=0.0, ge=0)
    seed: Count = Field(ge=0)


class CosimulationPrior(Section):
    """The target's zones (mean, std in update space) with normal score
    ``rho * z_src + sqrt(1 - rho^2) * z_new``; ``z_new`` has the source's variograms."""

    source: Literal["cosimulation"]
    from_: str = Field(alias="from", min_length=1)
    correlation: Number
    zones: tuple[Zone, ...] = Field(min_length=1)
    seed: Count = Field(ge=0)

    @field_validator("correlation")
    @classmethod
    def _rho(cls, rho: float) -> float:
        if not -1.0 <= rho <= 1.0:
            raise ValueError(f"correlation must lie in [-1, 1], got {rho}")
        return rho


class FilesPrior(Section):
    """The user's realisations: the files of ``folder`` matching ``pattern``, one per member in
    natural order (``poro_2`` before ``poro_10``), each holding ``keyword`` (default: the
    field's) for every cell of the grid or for every active cell. ``folder`` is relative to
    the case file (the loader resolves it)."""

    source: Literal["files"]
    folder: str = Field(min_length=1)
    pattern: str = Field(default="*.grdecl", min_length=1)
    keyword: str | None = None


Prior = Annotated[GeostatisticalPrior | RelationPrior | CosimulationPrior | FilesPrior,
                  Field(discriminator="source")]


class FieldSpec(Section):
    """One ``kind = "field"`` parameter (see the module's docstring)."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    kind: Literal["field"] = "field"
    keyword: str
    log: Annotated[bool, Strict()] | None = None
    low: Number | None = None
    high: Number | None = None
    copies: tuple[str, ...] = ()
    prior: Prior
    description: str = ""

    @field_validator("keyword")
    @classmethod
    def _keyword(cls, keyword: str) -> str:
        if keyword.upper() not in FIELD_KEYWORDS:
            raise ValueError(f"a field's keyword must be one of {list(FIELD_KEYWORDS)}, got "
                             f"{keyword!r}")
        return keyword.upper()

    @field_validator("copies")
    @classmethod
    def _copies(cls, copies: tuple[str, ...]) -> tuple[str, ...]:
        bad = [c for c in copies if c.upper() not in FIELD_KEYWORDS]
        if bad:
            raise ValueError(f"copies must be keywords among {list(FIELD_KEYWORDS)}, got {bad}")
        return tuple(c.upper() for c in copies)

    @model_validator(mode="after")
    def _check(self) -> FieldSpec:
        low, high = self.bounds
        if not low < high:
            raise ValueError(f"a field needs low < high, got low={low}, high={high}")
        if self.in_log and low <= 0:
            raise ValueError(f"a field in log space needs low > 0, got low={low} "
                             f"(keyword {self.keyword})")
        if self.keyword in FRACTIONS and not (0 < low and high <= 1):
            raise ValueError(f"{self.keyword} bounds must satisfy 0 < low and high <= 1 (a "
                             f"fraction; a cell without pore volume would become inactive), "
                             f"got low={low}, high={high}")
        if self.keyword in self.copies:
            raise ValueError(f"copies must not repeat the field's own keyword {self.keyword}")
        return self

    @property
    def in_log(self) -> bool:
        """Updated in log10 of the value: as stated, else for permeability only."""
        return self.keyword in PERMEABILITY if self.log is None else self.log

    @property
    def bounds(self) -> tuple[float, float]:
        """Physical (low, high), the keyword's defaults where the case gives none."""
        low, high = DEFAULT_BOUNDS[self.keyword]
        return (low if self.low is None else self.low, high if self.high is None else self.high)

    @property
    def written(self) -> tuple[str, ...]:
        """Every keyword a member's include sets: the field's, then its copies."""
        return (self.keyword, *self.copies)

    @property
    def source_field(self) -> str | None:
        """The name of the field this one's prior is drawn from (None when independent)."""
        return getattr(self.prior, "from_", None)
