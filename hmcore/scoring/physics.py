"""Physical validity of a proposal: the checks a reservoir engineer applies to a modified model.

Before the simulator runs, on the base deck's cells scaled by the proposal's multipliers
(:class:`hmcore.eclipse.cells.CellProperties`; box multipliers act on their box only):

* ``parameter_range`` - multipliers stay > 0, skins above -6 (more negative skins make
  connection factors meaningless for unstimulated wells);
* ``porosity_max`` / ``permeability_cap`` - the largest cell stays below ``poro_max`` and
  the permeability cap (``perm_cap_ratio`` x the deck's own largest value, or ``perm_cap_md``);
* ``kv_kh`` - per cell, kv/kh = PERMZ / sqrt(PERMX PERMY) in ``[kv_kh_min, kv_kh_max]``: the share
  of cells outside may grow by at most ``kv_kh_max_fraction`` over the deck's own share
  (PERMZ x3 with PERMX x0.3 gives 10x the deck's ratio);
* ``poro_perm_trend`` - the deck's own trend log10(kh) = a + b phi (least squares over its cells,
  residual sd s): the share of cells further than ``trend_sd`` x s from the trend, evaluated at
  their new porosity, may grow by at most ``trend_max_fraction``;
* ``pore_volume`` - the total pore volume changes by at most ``pore_volume_change_max``.

After the run, on the simulated well responses:

* ``pressure_min`` - no open well's simulated BHP below ``pressure_min`` (deck units; default
  one atmosphere: 1.01325 bar METRIC, 14.696 psia FIELD, 1 atm LAB);
* ``water_cut_range`` - simulated water cut inside [0, 1].

The penalty is graded, never an invented score: ``P = violation_weight * sum(excess)``, each
excess measuring how far past its limit the proposal goes (relative excess for a value, the
share of cells beyond the allowed share for a cell count). ``P = 0`` exactly when no check fires.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import pandas as pd

from hmcore.eclipse.deck_info import DeckInfo
from hmcore.model.parameters import ParameterSpace

SKIN_MIN = -6.0
ATMOSPHERE = {"METRIC": 1.01325, "FIELD": 14.696, "LAB": 1.0, "PVT-M": 1.0}
WATER_CUT_SLACK = 1e-6
PRESSURE_SLACK = 1e-3  # relative: summary files round 1 atm (14.696 psia) to float32


class Check(str, Enum):
    """The kinds of physics check (the ``kind`` of every violation)."""

    PARAMETER_RANGE = "parameter_range"
    POROSITY_MAX = "porosity_max"
    PERMEABILITY_CAP = "permeability_cap"
    KV_KH = "kv_kh"
    PORO_PERM_TREND = "poro_perm_trend"
    PORE_VOLUME = "pore_volume"
    PRESSURE_MIN = "pressure_min"
    WATER_CUT_RANGE = "water_cut_range"


CHECK_NAMES = {
    Check.PARAMETER_RANGE: "parameter outside its physical range",
    Check.POROSITY_MAX: "porosity above its maximum",
    Check.PERMEABILITY_CAP: "permeability above its cap",
    Check.KV_KH: "vertical to horizontal permeability ratio",
    Check.PORO_PERM_TREND: "porosity-permeability trend",
    Check.PORE_VOLUME: "pore volume change",
    Check.PRESSURE_MIN: "bottom-hole pressure below its minimum",
    Check.WATER_CUT_RANGE: "water cut outside 0 to 1",
}
"""Each check by the name a reservoir engineer reads (the report's; ``Check`` values are the
stored keys)."""


def check_name(kind: str) -> str:
    """The engineer's name of a stored check key (the key itself when it is not a check)."""
    try:
        return CHECK_NAMES[Check(kind)]
    except ValueError:
        return str(kind).replace("_", " ")


def check_sentence(kind: str, settings) -> str:
    """One sentence of what check ``kind`` tests and its limit under ``settings`` (a case's
    ``[physics]``, :class:`hmcore.model.case.PhysicsSettings`)."""
    s = settings
    cap = (f"{s.perm_cap_md:g} mD" if s.perm_cap_md is not None
           else f"{s.perm_cap_ratio:g} times the deck's own largest value")
    pmin = (f"{s.pressure_min:g} (deck units)" if s.pressure_min is not None
            else "one atmosphere")
    sentences = {
        Check.PARAMETER_RANGE: "Multipliers stay above 0 and skins above "
                               f"{SKIN_MIN:g} (a more negative skin makes the connection factor "
                               "of an unstimulated well meaningless).",
        Check.POROSITY_MAX: f"No cell's porosity after the multipliers exceeds {s.poro_max:g}.",
        Check.PERMEABILITY_CAP: f"No cell's permeability (x, y or z) exceeds {cap}.",
        Check.KV_KH: f"kv/kh = PERMZ / sqrt(PERMX PERMY) per cell lies in [{s.kv_kh_min:g}, "
                     f"{s.kv_kh_max:g}]: the share of cells outside may grow by at most "
                     f"{100 * s.kv_kh_max_fraction:g} points over the deck's own share.",
        Check.PORO_PERM_TREND: "Each cell's horizontal permeability stays within "
                               f"{s.trend_sd:g} standard deviations of the deck's own trend of "
                               "log-permeability against porosity (at the cell's new porosity): "
                               "the share of cells beyond may grow by at most "
                               f"{100 * s.trend_max_fraction:g} points over the deck's own share.",
        Check.PORE_VOLUME: "The total pore volume changes by at most "
                           f"{100 * s.pore_volume_change_max:g} % from the deck's.",
        Check.PRESSURE_MIN: "No open well's simulated bottom-hole pressure falls below "
                            f"{pmin}.",
        Check.WATER_CUT_RANGE: "Every simulated water cut lies between 0 and 1.",
    }
    try:
        return sentences[Check(kind)]
    except ValueError:
        return "A check this version of hmflow does not know."


@dataclass(frozen=True)
class Violation:
    kind: Check
    excess: float       # how far past the limit (> 0)
    message: str


@dataclass(frozen=True)
class PhysicsCheck:
    penalty: float
    found: tuple[Violation, ...] = ()
    runnable: bool = True  # False when the simulator could not even run (porosity >= 1, say)

    @property
    def violations(self) -> tuple[str, ...]:
        return tuple(v.message for v in self.found)

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(v.kind.value for v in self.found)

    @property
    def valid(self) -> bool:
        return not self.found

    def __add__(self, other: "PhysicsCheck") -> "PhysicsCheck":
        return PhysicsCheck(self.penalty + other.penalty, self.found + other.found,
                            self.runnable and other.runnable)


@dataclass(frozen=True)
class _Found:
    items: list[Violation] = field(default_factory=list)

    def add(self, kind: Check, excess: float, message: str) -> None:
        self.items.append(Violation(kind, float(excess), message))


def check_physics(values: dict[str, float], space: ParameterSpace, info: DeckInfo,
                  settings) -> PhysicsCheck:
    """The checks before any simulator time (``settings``: the case's ``[physics]``)."""
    found = _Found()
    runnable = True
    multipliers: list[tuple[str, float, tuple[int, ...] | None]] = []
    for p in space.parameters:
        if p.name not in values:
            continue
        v = float(values[p.name])
        if p.kind == "multiply":
            where = (p.region.upper(), tuple(p.region_numbers)) if p.region else p.box
            multipliers += [(kw.upper(), v, where) for kw in p.keywords]
            if v <= 0:
                found.add(Check.PARAMETER_RANGE, 1.0 + abs(v), f"{p.name}={v:g} must be > 0")
                runnable = False
        elif p.kind == "skin" and v < SKIN_MIN:
            found.add(Check.PARAMETER_RANGE, (SKIN_MIN - v) / abs(SKIN_MIN),
                      f"{p.name}={v:g} is below the physical floor {SKIN_MIN}")
    cells = info.cells
    if runnable and cells is not None and cells.n:
        factors = cells.factors(multipliers)
        runnable = _check_extremes(cells, factors, settings, found)
        _check_kv_kh(cells, factors, settings, found)
        _check_trend(cells, factors, settings, found)
        _check_pore_volume(cells, factors, settings, found)
    return PhysicsCheck(settings.violation_weight * sum(v.excess for v in found.items),
                        tuple(found.items), runnable)


def check_responses(responses: pd.DataFrame, info: DeckInfo, settings) -> PhysicsCheck:
    """The checks on a run's simulated well responses (well, quantity, days, value)."""
    found = _Found()
    pmin = settings.pressure_min if settings.pressure_min is not None else \
        ATMOSPHERE.get(info.unit_system, 1.0)
    bhp = responses[(responses.quantity == "WBHP") & (responses.value > 0)]  # 0: not yet open
    floor = pmin * (1.0 - PRESSURE_SLACK)  # a well held at the 1 atm limit is not below it
    if not bhp.empty and bhp.value.min() < floor:
        low = bhp[bhp.value < floor]
        worst = low.loc[low.value.idxmin()]
        found.add(Check.PRESSURE_MIN, (pmin - worst.value) / pmin,
                  f"simulated BHP {worst.value:.4g} below the minimum {pmin:g} "
                  f"({worst.well}, day {worst.days:g}; {low.well.nunique()} well(s))")
    wct = responses[responses.quantity == "WWCT"]
    if not wct.empty:
        out = np.maximum(wct.value - 1.0, -wct.value).to_numpy(float)
        if out.max() > WATER_CUT_SLACK:
            worst = wct.iloc[int(np.argmax(out))]
            found.add(Check.WATER_CUT_RANGE, float(out.max()),
                      f"simulated water cut {worst.value:.4g} outside [0, 1] "
                      f"({worst.well}, day {worst.days:g})")
    return PhysicsCheck(settings.violation_weight * sum(v.excess for v in found.items),
                        tuple(found.items))


def _scaled(cells, factors: dict[str, np.ndarray], kw: str) -> np.ndarray | None:
    base = cells.get(kw)
    if base is None:
        return None
    return base * factors[kw] if kw in factors else base


def _check_extremes(cells, factors, settings, found: _Found) -> bool:
    runnable = True
    poro = _scaled(cells, factors, "PORO")
    if poro is not None and "PORO" in factors and poro.max() > settings.poro_max:
        hi = float(poro.max())
        found.add(Check.POROSITY_MAX, (hi - settings.poro_max) / settings.poro_max,
                  f"max porosity {hi:.3f} > {settings.poro_max}")
        runnable = hi < 1.0
    for kw in ("PERMX", "PERMY", "PERMZ"):
        k = _scaled(cells, factors, kw)
        if k is None or kw not in factors:
            continue
        cap = permeability_cap(settings, float(cells.get(kw).max()))
        if k.max() > cap:
            hi = float(k.max())
            found.add(Check.PERMEABILITY_CAP, (hi - cap) / cap,
                      f"max {kw} {hi:.0f} mD > cap {cap:.0f} mD")
    return runnable


def permeability_cap(settings, deck_max_md: float) -> float:
    """The cap in mD: ``perm_cap_md`` when the case sets it, else ``perm_cap_ratio`` times the
    deck's own largest value (a field's permeability scale is its own: SPE9 reaches 10 D)."""
    if settings.perm_cap_md is not None:
        return float(settings.perm_cap_md)
    return settings.perm_cap_ratio * deck_max_md


def _horizontal(cells, factors) -> tuple[np.ndarray, np.ndarray] | None:
    """Deck and scaled kh = sqrt(PERMX PERMY) (PERMX alone when PERMY is absent)."""
    kx = cells.get("PERMX")
    if kx is None:
        return None
    own_y = cells.get("PERMY") is not None
    ky = cells.get("PERMY") if own_y else kx
    # PERMY's factor is its own; only a deck without PERMY (kx stands for it) follows PERMX's
    fy = factors.get("PERMY", 1.0) if own_y else factors.get("PERMX", 1.0)
    f = np.sqrt(factors.get("PERMX", 1.0) * fy)
    kh = np.sqrt(kx * ky)
    return kh, kh * f


def _check_kv_kh(cells, factors, settings, found: _Found) -> None:
    kz = cells.get("PERMZ")
    kh = _horizontal(cells, factors)
    if kz is None or kh is None or not ({"PERMX", "PERMY", "PERMZ"} & set(factors)):
        return
    kh0, kh1 = kh
    ok = kh0 > 0
    r0 = kz[ok] / kh0[ok]
    r1 = (kz * factors.get("PERMZ", 1.0))[ok] / kh1[ok]
    lo, hi = settings.kv_kh_min, settings.kv_kh_max
    _cell_share(found, Check.KV_KH, (r0 < lo) | (r0 > hi), (r1 < lo) | (r1 > hi),
                settings.kv_kh_max_fraction, f"kv/kh outside [{lo:g}, {hi:g}]")


def _cell_share(found: _Found, kind: Check, out_deck: np.ndarray, out_new: np.ndarray,
                allowed: float, what: str) -> None:
    """A cell check: the share of cells breaking it may grow by ``allowed`` over the deck's."""
    share0, share1 = float(np.mean(out_deck)), float(np.mean(out_new))
    grown = share1 - share0
    if grown > allowed:
        found.add(kind, grown - allowed,
                  f"{what} in {100 * share1:.1f} % of the cells (deck {100 * share0:.1f} %; at "
                  f"most +{100 * allowed:g} points allowed)")


def poro_perm_trend(poro: np.ndarray, kh: np.ndarray) -> tuple[float, float, float]:
    """The deck's trend log10(kh) = a + b phi over its cells with phi, kh > 0: (a, b, sd)."""
    ok = (poro > 0) & (kh > 0)
    if ok.sum() < 3 or np.ptp(poro[ok]) <= 0:
        return float(np.mean(np.log10(kh[ok]))) if ok.any() else 0.0, 0.0, float("nan")
    b, a = np.polyfit(poro[ok], np.log10(kh[ok]), 1)
    resid = np.log10(kh[ok]) - (a + b * poro[ok])
    return float(a), float(b), float(np.std(resid))


def _check_trend(cells, factors, settings, found: _Found) -> None:
    poro = cells.get("PORO")
    kh = _horizontal(cells, factors)
    if poro is None or kh is None or not ({"PORO", "PERMX", "PERMY"} & set(factors)):
        return
    kh0, kh1 = kh
    a, b, sd = poro_perm_trend(poro, kh0)
    if not sd > 0:
        return
    poro1 = poro * factors.get("PORO", 1.0)
    ok = (poro > 0) & (kh0 > 0)
    z0 = (np.log10(kh0[ok]) - (a + b * poro[ok])) / sd
    z1 = (np.log10(kh1[ok]) - (a + b * poro1[ok])) / sd
    _cell_share(found, Check.PORO_PERM_TREND, np.abs(z0) > settings.trend_sd,
                np.abs(z1) > settings.trend_sd, settings.trend_max_fraction,
                f"permeability beyond {settings.trend_sd:g} sd of the deck's "
                "porosity-permeability trend")


def _check_pore_volume(cells, factors, settings, found: _Found) -> None:
    porv = cells.get("PORV")
    f = factors.get("PORO", 1.0) * factors.get("NTG", 1.0)
    if porv is None or np.isscalar(f) or porv.sum() <= 0:
        return
    change = float((porv * f).sum() / porv.sum() - 1.0)
    limit = settings.pore_volume_change_max
    if abs(change) > limit:
        found.add(Check.PORE_VOLUME, (abs(change) - limit) / limit,
                  f"pore volume changes by {100 * change:+.1f} % (at most +-{100 * limit:g} %)")
