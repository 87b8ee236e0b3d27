"""Units of the matched quantities: what a deck's unit system uses, and conversion into it.

The simulator reports in the deck's units (``METRIC``, ``FIELD``, ``LAB`` or ``PVT-M``), so
observed values are compared in those units. An observed row may name its unit in the
``units`` column; it is converted when the unit is known for the quantity's dimension and
refused otherwise, with the deck's unit named. Gauge pressures are refused (they need the
atmospheric offset, which hmflow will not guess).
"""

from __future__ import annotations

from enum import Enum

import numpy as np


class Dimension(str, Enum):
    PRESSURE = "pressure"
    LIQUID_RATE = "liquid rate"
    GAS_RATE = "gas rate"
    GAS_LIQUID_RATIO = "gas-liquid ratio"
    FRACTION = "fraction"


DIMENSION_OF = {
    "WBHP": Dimension.PRESSURE, "WTHP": Dimension.PRESSURE,
    "WOPR": Dimension.LIQUID_RATE, "WWPR": Dimension.LIQUID_RATE,
    "WWIR": Dimension.LIQUID_RATE,
    "WGPR": Dimension.GAS_RATE, "WGIR": Dimension.GAS_RATE,
    "WGOR": Dimension.GAS_LIQUID_RATIO,
    "WWCT": Dimension.FRACTION,
}

_DAY, _HOUR = 86400.0, 3600.0
_STB, _FT3 = 0.158987294928, 0.028316846592
# SI factor of every accepted spelling (lower case, spaces removed), per dimension
_FACTORS: dict[Dimension, dict[str, float]] = {
    Dimension.PRESSURE: {
        "bar": 1e5, "bara": 1e5, "barsa": 1e5, "psia": 6894.757293168, "psi": 6894.757293168,
        "atm": 101325.0, "kpa": 1e3, "mpa": 1e6, "pa": 1.0,
    },
    Dimension.LIQUID_RATE: {
        "sm3/day": 1 / _DAY, "sm3/d": 1 / _DAY, "m3/day": 1 / _DAY, "m3/d": 1 / _DAY,
        "stb/day": _STB / _DAY, "stb/d": _STB / _DAY, "bbl/day": _STB / _DAY,
        "bbl/d": _STB / _DAY, "scc/hr": 1e-6 / _HOUR, "scc/h": 1e-6 / _HOUR,
    },
    Dimension.GAS_RATE: {
        "sm3/day": 1 / _DAY, "sm3/d": 1 / _DAY, "m3/day": 1 / _DAY, "m3/d": 1 / _DAY,
        "mscf/day": 1e3 * _FT3 / _DAY, "mscf/d": 1e3 * _FT3 / _DAY,
        "mmscf/day": 1e6 * _FT3 / _DAY, "mmscf/d": 1e6 * _FT3 / _DAY,
        "scf/day": _FT3 / _DAY, "scf/d": _FT3 / _DAY,
        "scc/hr": 1e-6 / _HOUR, "scc/h": 1e-6 / _HOUR,
    },
    Dimension.GAS_LIQUID_RATIO: {
        "sm3/sm3": 1.0, "m3/m3": 1.0, "scc/scc": 1.0,
        "mscf/stb": 1e3 * _FT3 / _STB, "scf/stb": _FT3 / _STB,
    },
    Dimension.FRACTION: {"fraction": 1.0, "frac": 1.0, "-": 1.0, "%": 0.01, "percent": 0.01},
}
_GAUGE = ("psig", "barg", "kpag")

# the unit each unit system reports in (as the simulator writes it in the SMSPEC file)
DECK_UNITS: dict[str, dict[Dimension, str]] = {
    "METRIC": {Dimension.PRESSURE: "bar", Dimension.LIQUID_RATE: "sm3/day",
               Dimension.GAS_RATE: "sm3/day", Dimension.GAS_LIQUID_RATIO: "sm3/sm3",
               Dimension.FRACTION: "fraction"},
    "FIELD": {Dimension.PRESSURE: "psia", Dimension.LIQUID_RATE: "stb/day",
              Dimension.GAS_RATE: "mscf/day", Dimension.GAS_LIQUID_RATIO: "mscf/stb",
              Dimension.FRACTION: "fraction"},
    "LAB": {Dimension.PRESSURE: "atm", Dimension.LIQUID_RATE: "scc/hr",
            Dimension.GAS_RATE: "scc/hr", Dimension.GAS_LIQUID_RATIO: "scc/scc",
            Dimension.FRACTION: "fraction"},
    "PVT-M": {Dimension.PRESSURE: "atm", Dimension.LIQUID_RATE: "sm3/day",
              Dimension.GAS_RATE: "sm3/day", Dimension.GAS_LIQUID_RATIO: "sm3/sm3",
              Dimension.FRACTION: "fraction"},
}


def normalise(unit: str) -> str:
    """A unit as written (``'STB/D'``, ``' bar '``) -> its lookup spelling (``'stb/d'``)."""
    return "".join(str(unit).split()).lower()


def deck_unit(quantity: str, unit_system: str) -> str:
    """The unit ``quantity`` has in a deck of ``unit_system``."""
    return DECK_UNITS[unit_system][DIMENSION_OF[quantity]]


def factor_to_deck(quantity: str, unit: str, unit_system: str) -> float:
    """The factor taking a value of ``quantity`` in ``unit`` into the deck's unit.

    Raises ValueError naming the accepted units when ``unit`` is unknown, of another
    dimension, or a gauge pressure.
    """
    dim = DIMENSION_OF[quantity]
    target = deck_unit(quantity, unit_system)
    u = normalise(unit)
    if u in _GAUGE:
        raise ValueError(f"{quantity} in gauge pressure '{unit}' cannot be compared with the "
                         f"simulator's absolute pressure ({target}); convert it to absolute "
                         "pressure (psia = psig + 14.696) and name the absolute unit")
    known = _FACTORS[dim]
    if u not in known:
        other = [d.value for d, f in _FACTORS.items() if u in f and d != dim]
        why = (f"'{unit}' is a {other[0]} unit, not a {dim.value}" if other
               else f"unknown unit '{unit}'")
        raise ValueError(f"{quantity}: {why}; this deck ({unit_system}) reports {quantity} in "
                         f"{target}; accepted units for a {dim.value}: {sorted(known)}")
    return known[u] / known[normalise(target)]


def convert(values: np.ndarray, quantity: str, unit: str, unit_system: str) -> np.ndarray:
    """``values`` of ``quantity`` in ``unit`` -> the deck's unit (ValueError as above)."""
    return np.asarray(values, dtype=float) * factor_to_deck(quantity, unit, unit_system)
