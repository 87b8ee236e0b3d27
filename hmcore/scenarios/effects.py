"""Hidden effects: one extension of the model that the truth has and the calibration space
lacks - a library candidate (:mod:`hmcore.diagnosis.extensions`) and its true value; drawn from a
seed within realistic strengths, chosen by id, or read back from a ``hidden_effect.json``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hmcore.diagnosis.candidate import KINDS, Candidate
from hmcore.diagnosis.extensions import build_candidates
from hmcore.eclipse.deck_info import DeckInfo
from hmcore.model.parameters import Parameter, ParameterSpace

STRENGTH = {
    # kind: ((low, high) of a decrease, (low, high) of an increase, P(decrease)); factors or
    # skin increments (well_skin) / exponents (relative_permeability)
    "well_skin": ((-6.0, -4.0), (8.0, 15.0), 0.25),
    "regional_permeability": ((0.15, 0.35), (3.0, 6.0), 0.6),
    "layer_permeability": ((0.15, 0.3), (3.0, 5.0), 0.5),
    "vertical_permeability": ((0.001, 0.01), (30.0, 100.0), 1.0),
    "aquifer_strength": ((0.03, 0.12), (5.0, 15.0), 0.5),
    "fault_transmissibility": ((1e-3, 1e-2), (1e-3, 1e-2), 1.0),
    "relative_permeability": ((0.4, 0.55), (2.2, 2.9), 0.5),
    "contact_depth": ((0.992, 0.997), (1.003, 1.008), 0.5),
    "solution_gas": ((0.85, 0.93), (0.85, 0.93), 1.0),
}
"""Realistic ranges of hidden effects, log-uniform for multipliers. Vertical permeability is
drawn as a baffle (kv cut 100-1000 times): raising kv changes nothing once it is not the
bottleneck. An aquifer productivity index is drawn weaker (see :data:`STRENGTH_OVERRIDES`)."""


STRENGTH_OVERRIDES = {"aquifer_strength:AQUFETP:6": ((0.005, 0.03), (0.005, 0.03), 1.0),
                      "relative_permeability:water:endpoint": ((-0.10, -0.05), (0.05, 0.10), 0.5),
                      "relative_permeability:gas:endpoint": ((-0.10, -0.05), (0.05, 0.10), 0.5)}
"""Per-candidate ranges (id prefix): a Fetkovich aquifer's productivity index matters only
when it, not the grid, limits the influx, i.e. when it is much weaker than the deck's; a
critical-saturation shift is a saturation change (uniform, added), not a factor."""


@dataclass(frozen=True)
class HiddenEffect:
    """One hidden extension: the library candidate and its true value."""

    candidate: Candidate
    value: float

    @property
    def kind(self) -> str:
        return self.candidate.kind

    @property
    def parameter(self) -> Parameter:
        return self.candidate.parameter

    def to_dict(self) -> dict:
        return {"id": self.candidate.id, "kind": self.kind, "wells": list(self.candidate.wells),
                "layers": list(self.candidate.layers), "value": self.value,
                "parameter": self.parameter.model_dump(mode="json"),
                "description": self.candidate.description,
                "generated": self.candidate.details.get("generated"),
                "expect_wells": self.candidate.details.get("expect_wells") or [],
                "expect_ids": self.candidate.details.get("expect_ids") or [],
                "start_day": self.candidate.details.get("start_day"),
                **({"expect_kinds": self.candidate.details["expect_kinds"]}
                   if self.candidate.details.get("expect_kinds") else {})}

    @property
    def generated(self) -> str | None:
        """The generator that made it (:mod:`hmcore.scenarios.generators`), None for a
        library candidate."""
        return self.candidate.details.get("generated")


def chosen_effect(candidate_id: str, value: float, info: DeckInfo, space: ParameterSpace,
                  values: dict[str, float]) -> HiddenEffect:
    """The library candidate ``candidate_id`` (see :func:`build_candidates`) at ``value``.

    Raises ValueError naming the known ids of the kind, or the bounds the value breaks."""
    kind = candidate_id.split(":", 1)[0]
    if kind not in KINDS:
        raise ValueError(f"candidate id {candidate_id!r} must start with a kind of {list(KINDS)}"
                         ", e.g. 'well_skin:PROD2'")
    cands = build_candidates(info, space, values, (kind,))
    c = next((c for c in cands if c.id == candidate_id), None)
    if c is None:
        raise ValueError(f"the deck {info.path} offers no candidate {candidate_id!r}; its "
                         f"{kind} candidates are {[c.id for c in cands]}")
    p = c.parameter
    if not p.low <= value <= p.high:
        raise ValueError(f"{candidate_id}: low <= value <= high must hold, got value={value:g}, "
                         f"low={p.low:g}, high={p.high:g}")
    return HiddenEffect(c, float(value))


def _effect_of(e: dict) -> HiddenEffect:
    details = {"generated": e["generated"], "expect_wells": e.get("expect_wells") or [],
               "expect_ids": e.get("expect_ids") or []} if e.get("generated") else {}
    if e.get("start_day") is not None:
        details["start_day"] = float(e["start_day"])
    if e.get("expect_kinds"):
        details["expect_kinds"] = list(e["expect_kinds"])
    c = Candidate(id=e["id"], kind=e["kind"], parameter=Parameter.model_validate(e["parameter"]),
                  wells=tuple(e.get("wells", ())), layers=tuple(e.get("layers", ())),
                  description=e.get("description", ""), details=details)
    return HiddenEffect(c, float(e["value"]))


def load_hidden_effects(path: Path) -> list[HiddenEffect]:
    """Every effect a ``hidden_effect.json`` (written by the ``write_hidden_*`` functions)
    describes; empty for a control."""
    doc = json.loads(Path(path).read_text())
    if isinstance(doc, dict) and "effects" in doc:
        return [_effect_of(e) for e in doc["effects"]]
    e = doc.get("effect") if isinstance(doc, dict) and "truth" in doc else doc
    return [] if e is None else [_effect_of(e)]


def load_hidden_effect(path: Path) -> HiddenEffect | None:
    """The (first) effect a ``hidden_effect.json`` describes; None for a control."""
    effects = load_hidden_effects(path)
    return effects[0] if effects else None


def draw_library_effect(kind: str, seed: int, info: DeckInfo, space: ParameterSpace,
                values: dict[str, float], choices: list[str] | None = None) -> HiddenEffect:
    """A random candidate of ``kind`` (optionally among ids ``choices``) and strength."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}")
    if kind == "productivity_change":
        raise ValueError("a productivity change is dated: draw it with "
                         "hmcore.scenarios.generators.draw_effect")
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    every = build_candidates(info, space, values, (kind,))
    cands = [c for c in every if choices is None or c.id in choices]
    if not cands:
        raise ValueError(f"the deck {info.path} offers no {kind} candidate"
                         + (f" among {choices}; its {kind} candidates are "
                            f"{[c.id for c in every]}" if choices is not None else ""))
    c = cands[int(rng.integers(len(cands)))]
    spec = next((v for k, v in STRENGTH_OVERRIDES.items() if c.id.startswith(k)), STRENGTH[kind])
    (dlo, dhi), (ulo, uhi), p_down = spec
    lo, hi = (dlo, dhi) if rng.random() < p_down else (ulo, uhi)
    if kind == "well_skin":
        value = c.neutral + float(rng.uniform(lo, hi))
    elif c.parameter.mode == "endpoint":  # a shift; none below a table's first row
        value = c.neutral + float(rng.uniform(lo, hi))
        value = -value if value < c.parameter.low else value
    else:
        value = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    value = float(np.clip(value, c.parameter.low, c.parameter.high))
    return HiddenEffect(c, value)
