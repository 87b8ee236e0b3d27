"""A model extension as data: :class:`Candidate` (one physical hypothesis as one new parameter),
the families' names (:data:`KINDS`), their ranges and probes, and the deck facts the families
read (a well's column and skin, the wells on one side of a plane). The families that build the
candidates are :mod:`hmcore.diagnosis.extensions`'.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hmcore.diagnosis.recalibrate import Coordinates
from hmcore.eclipse.deck_info import DeckInfo
from hmcore.model.deck_values import deck_skins
from hmcore.model.parameters import Parameter, ParameterSpace
from hmcore.ordering import natural_key

KINDS = ("well_skin", "regional_permeability", "layer_permeability", "vertical_permeability",
         "aquifer_strength", "fault_transmissibility", "relative_permeability",
         "productivity_change", "contact_depth", "solution_gas")
"""The families (appended only: a kind's index seeds its hidden effects' draws)."""
DEFAULT_KINDS = KINDS[:8]
"""The families a diagnosis searches unless told (``kinds``): all but ``contact_depth`` and
``solution_gas``, which are searched when asked for until a sweep has measured what they do
to the answers (why: docs/diagnosis.md, the extension kinds)."""

REGION_HALF_WIDTH = 3
"""Half width (cells) of the box of a regional permeability candidate."""
PERM_BOUNDS = (0.1, 10.0)
PERMZ_BOUNDS = (0.01, 100.0)
AQUIFER_BOUNDS = (0.05, 20.0)
FAULT_BOUNDS = (1e-4, 1.0)
RELPERM_BOUNDS = (0.4, 3.0)
RELPERM_SCALE_BOUNDS = (0.2, 5.0)
RELPERM_SCALE_PROBE = 0.6
"""Probe of a relative-permeability factor: down, since a factor up is capped at 1."""
RELPERM_ENDPOINT_BOUNDS = (-0.2, 0.2)
RELPERM_ENDPOINT_PROBE = 0.05
"""Probe of a critical-saturation shift (saturation units): up, since a table that starts at
its critical saturation has no room below it."""
WELL_SKIN_BOUNDS = (-5.0, 30.0)
PI_BOUNDS = (0.05, 20.0)
CONTACT_BOUNDS = (0.98, 1.02)
"""Factor on a contact's depth: +-2 %, some 50 m at 2,500 m, more than a reservoir's oil
column is often thick."""
SOLUTION_GAS_BOUNDS = (0.5, 1.0)
"""Factor on the initial Rs (or bubble point): at most the deck's, since oil at a gas cap is
saturated, and more gas than saturated oil holds is no initial state (the high end is a
physical limit, :data:`LIMIT_ENDS`)."""
LIMIT_ENDS = {"fault_transmissibility": ("low", "high"), "vertical_permeability": ("low",),
              "aquifer_strength": ("low",), "solution_gas": ("high",)}
"""The ends of a family's range that are a physical limit - a sealed fault (and no fault), a
layer that is a vertical barrier, next to no aquifer: a fit there is a complete effect. At any
other end (:func:`open_end`) the data ask the family for more than its range holds."""
PROBE = {"well_skin": 6.0, "regional_permeability": 0.4, "layer_permeability": 0.4,
         "vertical_permeability": 0.1, "aquifer_strength": 0.3,
         "fault_transmissibility": 0.01, "relative_permeability": 1.6,
         "productivity_change": 0.5, "contact_depth": 1.005, "solution_gas": 0.9}
"""Finite-difference probe: skin increment, or factor (multipliers), or exponent."""


@dataclass(frozen=True)
class Candidate:
    """One model extension: a new parameter, what it means and where it acts."""

    id: str
    kind: str
    parameter: Parameter
    wells: tuple[str, ...] = ()
    layers: tuple[int, ...] = ()
    description: str = ""
    neutral: float = 1.0
    probe: float = 1.0
    details: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.parameter.name

    def machine(self) -> dict:
        """The extension as data: kind, wells, layers and the parameter definition."""
        return {"id": self.id, "kind": self.kind, "wells": list(self.wells),
                "layers": list(self.layers), "neutral": self.neutral, "probe": self.probe,
                "parameter": self.parameter.model_dump(mode="json"), **self.details}


def open_end(c: Candidate, value: float, near: float) -> str | None:
    """``"low"`` or ``"high"`` when ``value`` lies within ``near`` (scaled distance, the
    recalibration's coordinates: log scale for multipliers) of that end of ``c``'s range and
    that end is not a physical limit of the family (:data:`LIMIT_ENDS`); else None.

    A recalibrated candidate that stops there fits the data only as far as its range lets it:
    it stands in for an effect it does not describe - or for a larger effect of its own kind,
    beyond the range a user would call plausible (examples: docs/diagnosis.md, "A cause at the
    end of its range is flagged")."""
    if near < 0:
        return None
    (u,) = Coordinates([c.parameter]).to_u({c.name: value})
    end = "high" if u >= 1.0 - near else "low" if u <= -1.0 + near else None
    if end == "low" and c.details.get("low_is_limit"):  # e.g. a table's first row
        return None
    return None if end is None or end in LIMIT_ENDS.get(c.kind, ()) else end


# ----------------------------------------------------------------------------- deck facts
def current_skin(well: str, space: ParameterSpace, values: dict[str, float],
                 info: DeckInfo) -> float:
    """The skin ``well`` has in the model with ``values`` (the last skin parameter touching it,
    else the deck's)."""
    skin = deck_skins(info).get(well, 0.0)
    for p in space.parameters:
        if p.kind == "skin" and p.name in values and not p.layers:
            targets = p.wells or tuple(info.producers)
            if well in targets:
                skin = float(values[p.name])
    return skin


def well_column(info: DeckInfo, well: str) -> tuple[int, int]:
    """(i, j) of a well's first connection (1-based)."""
    conns = info.wells[well].connections
    i, j, _ = conns[0]
    return i, j


def wells_below(info: DeckInfo, axis: str, plane: int) -> list[str]:
    """The producers on the low side of the plane ``plane | plane + 1`` along ``axis`` ("i" or
    "j"), in natural order."""
    k = 0 if axis == "i" else 1
    return sorted((w for w in info.producers if well_column(info, w)[k] <= plane),
                  key=natural_key)


def extended_space(space: ParameterSpace, candidates: list[Candidate]) -> ParameterSpace:
    """``space`` followed by the candidates' parameters (after the globals, so a well's own
    skin overrides a global skin)."""
    return ParameterSpace(parameters=tuple(space.parameters) + tuple(c.parameter for c in candidates))


def slug(name: str) -> str:
    """``name`` with every character that is not a letter or digit as ``_`` (a parameter name)."""
    return "".join(ch if ch.isalnum() else "_" for ch in name)
