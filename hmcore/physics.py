"""Physical validity of a parameter vector, checked on the scaled deck properties.

Rules (limits from the case's ``[physics]`` settings): porosity stays in (0, poro_max];
permeabilities stay positive and below ``perm_cap_md``; skin stays above -6 (more negative
skins make connection factors meaningless for unstimulated wells). The penalty grows with the
relative size of each violation: ``P = weight * sum(relative excess)``; it is 0 when valid.
Box-limited multipliers are assumed to reach the extreme cell (conservative).
"""

from __future__ import annotations

from dataclasses import dataclass

from hmcore.deck_info import DeckInfo
from hmcore.parameters import ParameterSpace

SKIN_MIN = -6.0


@dataclass(frozen=True)
class PhysicsCheck:
    penalty: float
    violations: tuple[str, ...]
    runnable: bool  # False when the simulator could not even run (porosity >= 1, say)

    @property
    def valid(self) -> bool:
        return not self.violations


def check_physics(values: dict[str, float], space: ParameterSpace, info: DeckInfo,
                  perm_cap_md: float, poro_max: float, weight: float) -> PhysicsCheck:
    factors: dict[str, float] = {}
    violations: list[str] = []
    excess = 0.0
    runnable = True
    for p in space.parameters:
        if p.name not in values:
            continue
        v = float(values[p.name])
        if p.kind == "multiply":
            for kw in p.keywords:
                factors[kw.upper()] = factors.get(kw.upper(), 1.0) * v
            if v <= 0:
                violations.append(f"{p.name}={v:g} must be > 0")
                excess += 1.0 + abs(v)
                runnable = False
        elif p.kind == "skin" and v < SKIN_MIN:
            violations.append(f"{p.name}={v:g} is below the physical floor {SKIN_MIN}")
            excess += (SKIN_MIN - v) / abs(SKIN_MIN)
    if "PORO" in info.properties and "PORO" in factors:
        hi = info.properties["PORO"][1] * factors["PORO"]
        if hi > poro_max:
            violations.append(f"max porosity {hi:.3f} > {poro_max}")
            excess += (hi - poro_max) / poro_max
            runnable = runnable and hi < 1.0
    for kw in ("PERMX", "PERMY", "PERMZ"):
        if kw in info.properties and kw in factors:
            hi = info.properties[kw][1] * factors[kw]
            if hi > perm_cap_md:
                violations.append(f"max {kw} {hi:.0f} mD > cap {perm_cap_md:.0f} mD")
                excess += (hi - perm_cap_md) / perm_cap_md
    return PhysicsCheck(weight * excess, tuple(violations), runnable)
