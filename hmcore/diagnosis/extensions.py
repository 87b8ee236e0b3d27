"""The library of model extensions: declared parameter families, each producing candidates.

A :class:`~hmcore.diagnosis.candidate.Candidate` is one physical hypothesis ("PROD3's completion is more damaged than the
others", "a sealing fault between the west and east wells") represented by one new
:class:`~hmcore.model.parameters.Parameter` of an existing kind, with

* ``kind`` (one of :data:`KINDS`), ``wells`` and ``layers`` (1-based k) it concerns;
* ``description`` in plain words and :meth:`Candidate.machine` (the parameter as data);
* ``neutral``: the value that reproduces the unextended model, and ``probe``: the value of the
  one finite-difference run used to rank it (see :mod:`hmcore.diagnosis.attribution`).

Families (see :func:`build_candidates`):

``well_skin``               COMPDAT skin of one well (kind ``skin``, ``wells=(w,)``)
``regional_permeability``   PERMX and PERMY in a box of +-3 cells around one well, all layers
``layer_permeability``      PERMX and PERMY in one layer k
``vertical_permeability``   PERMZ in one layer k (and globally, unless the case already has a
                            global PERMZ multiplier)
``aquifer_strength``        AQUCT item 4 (permeability) or AQUFETP item 4 (volume) / item 6
                            (productivity index), per aquifer
``fault_transmissibility``  MULTX (MULTY) on a plane i = i0 (j = j0) between two groups of
                            wells, through all layers
``relative_permeability``   exponent of the water table's krw (SWOF/SWFN column 2) and of the
                            gas table's krg (SGOF/SGFN column 2): the curve's shape; a
                            factor on each (``...:scale``, capped at 1): its level; and a
                            shift of each curve's critical saturation (``...:endpoint``,
                            SWCR / SGCR): where it starts to flow
``contact_depth``           the depth of the initial water-oil (EQUIL item 3) and gas-oil
                            (item 5) contact, each a factor on the depth of every EQUIL record
                            (one per equilibration region): where the phases start
``solution_gas``            the initial dissolved gas-oil ratio, a factor on the Rs column of
                            RSVD (or the bubble point of PBVD): what the oil holds in solution
``productivity_change``     the productivity index of one well multiplied from a report date
                            on (``WPIMULT`` in the schedule, kind ``wpimult`` with
                            ``start_day``): damage, scale or a stimulation during the history.
                            Its candidates are dated by the ranking from the residuals
                            (:func:`dated_productivity`, :mod:`hmcore.diagnosis.dating`), so
                            the family itself builds none and searches ``well_skin`` with it
                            (the date scan reads the well-skin probes)
"""

from __future__ import annotations

from datetime import timedelta

import numpy as np

from hmcore.eclipse.deck_info import DeckInfo
from hmcore.eclipse.tables import width
from hmcore.diagnosis.candidate import (
    AQUIFER_BOUNDS,
    CONTACT_BOUNDS,
    DEFAULT_KINDS,
    FAULT_BOUNDS,
    KINDS,
    PERM_BOUNDS,
    PERMZ_BOUNDS,
    PI_BOUNDS,
    PROBE,
    REGION_HALF_WIDTH,
    RELPERM_BOUNDS,
    RELPERM_ENDPOINT_BOUNDS,
    RELPERM_ENDPOINT_PROBE,
    RELPERM_SCALE_BOUNDS,
    RELPERM_SCALE_PROBE,
    SOLUTION_GAS_BOUNDS,
    WELL_SKIN_BOUNDS,
    Candidate,
    current_skin,
    slug,
    well_column,
    wells_below,
)
from hmcore.model.deck_values import deck_blocks
from hmcore.model.parameters import Parameter, ParameterSpace
from hmcore.model.run_deck import critical_saturation
from hmcore.ordering import natural_key

# ----------------------------------------------------------------------------- families
def _has_global(space: ParameterSpace, keyword: str) -> bool:
    return any(p.kind == "multiply" and p.box is None and keyword in [k.upper() for k in p.keywords]
               for p in space.parameters)


def well_skin(info: DeckInfo, space: ParameterSpace, values: dict[str, float]) -> list[Candidate]:
    out = []
    for well in sorted(info.producers, key=natural_key):
        s0 = current_skin(well, space, values, info)
        lo, hi = WELL_SKIN_BOUNDS
        lo, hi = min(lo, s0 - 1.0), max(hi, s0 + 1.0)
        probe = s0 + PROBE["well_skin"] if s0 + PROBE["well_skin"] <= hi else s0 - PROBE["well_skin"]
        p = Parameter(name=f"skin_{slug(well)}", kind="skin", wells=(well,), low=lo, high=hi,
                      description=f"skin of well {well}")
        out.append(Candidate(f"well_skin:{well}", "well_skin", p, (well,), (),
                             f"well {well} has a different completion skin (formation damage or "
                             "stimulation) than the other wells", s0, probe))
    return out


def regional_permeability(info: DeckInfo, space: ParameterSpace,
                          values: dict[str, float]) -> list[Candidate]:
    nx, ny, nz = info.dims
    h = REGION_HALF_WIDTH
    out = []
    for well in sorted(info.producers, key=natural_key):
        i, j = well_column(info, well)
        box = (max(1, i - h), min(nx, i + h), max(1, j - h), min(ny, j + h), 1, nz)
        p = Parameter(name=f"perm_region_{slug(well)}", kind="multiply",
                      keywords=("PERMX", "PERMY"), box=box, low=PERM_BOUNDS[0],
                      high=PERM_BOUNDS[1],
                      description=f"PERMX and PERMY multiplier around {well}")
        out.append(Candidate(f"regional_permeability:{well}", "regional_permeability", p,
                             (well,), (),
                             f"the rock around well {well} (cells i {box[0]}-{box[1]}, j "
                             f"{box[2]}-{box[3]}, all layers) is more or less permeable than "
                             "the model says", 1.0, PROBE["regional_permeability"],
                             {"box": list(box)}))
    return out


SHIFTS = tuple((si, sj) for si in (-1, 0, 1) for sj in (-1, 0, 1) if (si, sj) != (0, 0))
"""Directions a regional box is moved in by :func:`shifted_regions` (times its half width)."""


def shifted_regions(info: DeckInfo, well: str, taken: list[tuple[int, ...]] = ()
                    ) -> list[Candidate]:
    """The box of ``regional_permeability:<well>`` moved by its half width in i, j or both
    (:data:`SHIFTS`): a region beside the well, the well on its edge or at its corner. A moved
    box that the grid's edge cuts to fewer than half width + 1 cells across, or that equals a
    box in ``taken`` (another candidate's), is left out. The ranking probes these for the
    wells whose centred box scores beyond noise (:mod:`hmcore.diagnosis.workflow`)."""
    nx, ny, nz = info.dims
    h = REGION_HALF_WIDTH
    i, j = well_column(info, well)
    seen = {tuple(b) for b in taken}
    seen.add((max(1, i - h), min(nx, i + h), max(1, j - h), min(ny, j + h), 1, nz))
    out = []
    for si, sj in SHIFTS:
        ci, cj = i + si * h, j + sj * h
        box = (max(1, ci - h), min(nx, ci + h), max(1, cj - h), min(ny, cj + h), 1, nz)
        if box in seen or box[1] - box[0] < h or box[3] - box[2] < h:
            continue
        seen.add(box)
        where = f"i{box[0]}-{box[1]}:j{box[2]}-{box[3]}"
        p = Parameter(name=f"perm_region_{slug(well)}_{where.replace(':', '_').replace('-', '_')}",
                      kind="multiply", keywords=("PERMX", "PERMY"), box=box,
                      low=PERM_BOUNDS[0], high=PERM_BOUNDS[1],
                      description=f"PERMX and PERMY multiplier of cells i {box[0]}-{box[1]}, "
                                  f"j {box[2]}-{box[3]} (beside {well})")
        out.append(Candidate(f"regional_permeability:{well}:{where}", "regional_permeability",
                             p, (well,), (),
                             f"the rock beside well {well} (cells i {box[0]}-{box[1]}, j "
                             f"{box[2]}-{box[3]}, all layers: the box around it moved "
                             f"{h} cells) is more or less permeable than the model says",
                             1.0, PROBE["regional_permeability"],
                             {"box": list(box), "shift": [si * h, sj * h]}))
    return out


def layer_permeability(info: DeckInfo, space: ParameterSpace,
                       values: dict[str, float]) -> list[Candidate]:
    nx, ny, nz = info.dims
    out = []
    for k in range(1, nz + 1):
        wells = tuple(w for w in sorted(info.producers, key=natural_key)
                      if any(c[2] == k for c in info.wells[w].connections))
        p = Parameter(name=f"perm_layer{k}", kind="multiply", keywords=("PERMX", "PERMY"),
                      box=(1, nx, 1, ny, k, k), low=PERM_BOUNDS[0], high=PERM_BOUNDS[1],
                      description=f"PERMX and PERMY multiplier of layer {k}")
        out.append(Candidate(f"layer_permeability:{k}", "layer_permeability", p, wells, (k,),
                             f"layer {k} is more or less permeable (horizontally) than the model "
                             "says", 1.0, PROBE["layer_permeability"]))
    return out


def vertical_permeability(info: DeckInfo, space: ParameterSpace,
                          values: dict[str, float]) -> list[Candidate]:
    if "PERMZ" not in info.properties:
        return []
    nx, ny, nz = info.dims
    out = []
    if not _has_global(space, "PERMZ"):
        p = Parameter(name="permz_global", kind="multiply", keywords=("PERMZ",),
                      low=PERMZ_BOUNDS[0], high=PERMZ_BOUNDS[1],
                      description="global PERMZ multiplier")
        out.append(Candidate("vertical_permeability:all", "vertical_permeability", p, (), (),
                             "vertical permeability is different everywhere (kv/kh)", 1.0,
                             PROBE["vertical_permeability"]))
    for k in range(1, nz + 1):
        p = Parameter(name=f"permz_layer{k}", kind="multiply", keywords=("PERMZ",),
                      box=(1, nx, 1, ny, k, k), low=PERMZ_BOUNDS[0], high=PERMZ_BOUNDS[1],
                      description=f"PERMZ multiplier of layer {k}")
        out.append(Candidate(f"vertical_permeability:{k}", "vertical_permeability", p, (), (k,),
                             f"layer {k} lets fluids through vertically more or less than the "
                             "model says (a shale baffle or fractures)", 1.0,
                             PROBE["vertical_permeability"]))
    return out


def aquifer_strength(info: DeckInfo, space: ParameterSpace,
                     values: dict[str, float]) -> list[Candidate]:
    blocks = deck_blocks(info)
    out = []
    specs = []
    if "AQUCT" in blocks:
        specs.append(("AQUCT", 4, "permeability", "aquifer_perm"))
    if "AQUFETP" in blocks:
        specs.append(("AQUFETP", 4, "volume", "aquifer_volume"))
        specs.append(("AQUFETP", 6, "productivity index", "aquifer_pi"))
    for keyword, item, what, stem in specs:
        recs = [r for r in blocks[keyword] if len(r) >= item and r[item - 1] != "1*"]
        ids = [r[0].strip("'\"") for r in recs]
        if not ids:
            continue
        several = len(ids) > 1
        for aq in ids:
            match = aq if several else None
            name = f"{stem}{aq}" if several else stem
            p = Parameter(name=name, kind="item_multiply", keywords=(keyword,), item=item,
                          match=match, low=AQUIFER_BOUNDS[0], high=AQUIFER_BOUNDS[1],
                          description=f"{keyword} item {item} ({what}) multiplier"
                                      + (f" of aquifer {aq}" if several else ""))
            out.append(Candidate(f"aquifer_strength:{keyword}:{item}:{aq}", "aquifer_strength", p,
                                 (), (),
                                 f"the aquifer{f' {aq}' if several else ''} is stronger or weaker "
                                 f"than the model says ({keyword} {what})", 1.0,
                                 PROBE["aquifer_strength"],
                                 {"keyword": keyword, "item": item, "aquifer": aq}))
    return out


def fault_transmissibility(info: DeckInfo, space: ParameterSpace,
                           values: dict[str, float]) -> list[Candidate]:
    """Barrier planes between neighbouring well columns, in I (MULTX) and J (MULTY)."""
    nx, ny, nz = info.dims
    cols = {w: well_column(info, w) for w in info.producers}
    out = []
    for axis, keyword, n_along in (("i", "MULTX", nx), ("j", "MULTY", ny)):
        pos = sorted({c[0] if axis == "i" else c[1] for c in cols.values()})
        for a, b in zip(pos, pos[1:]):
            if b - a < 1:
                continue
            p0 = (a + b) // 2  # the barrier is the face between cell p0 and p0 + 1
            if axis == "i":
                box = (p0, p0, 1, ny, 1, nz)
            else:
                box = (1, nx, p0, p0, 1, nz)
            side_a = wells_below(info, axis, p0)
            side_b = sorted(set(cols) - set(side_a), key=natural_key)
            words = ("west", "east") if axis == "i" else ("south", "north")
            p = Parameter(name=f"fault_{axis}{p0}", kind="multiply", keywords=(keyword,), box=box,
                          low=FAULT_BOUNDS[0], high=FAULT_BOUNDS[1],
                          description=f"{keyword} on the plane {axis} = {p0} | {p0 + 1}")
            out.append(Candidate(
                f"fault_transmissibility:{axis}{p0}", "fault_transmissibility", p,
                tuple(side_a + side_b), (),
                f"a sealing or partly sealing fault between {axis} = {p0} and {p0 + 1} "
                f"separates the {words[0]} wells ({', '.join(side_a)}) from the {words[1]} "
                f"wells ({', '.join(side_b)})", 1.0, PROBE["fault_transmissibility"],
                {"plane": f"{axis}={p0}|{p0 + 1}", "box": list(box),
                 "groups": [side_a, side_b]}))
    return out


def relative_permeability(info: DeckInfo, space: ParameterSpace,
                          values: dict[str, float]) -> list[Candidate]:
    names = info.keyword_names
    out = []
    for phase, tables in (("water", ("SWOF", "SWFN")), ("gas", ("SGOF", "SGFN"))):
        table = next((t for t in tables if t in names), None)
        if table is None:
            continue
        short = "krw" if phase == "water" else "krg"
        p = Parameter(name=f"{short}_exponent", kind="relperm", keywords=(table,), item=2,
                      mode="power", low=RELPERM_BOUNDS[0], high=RELPERM_BOUNDS[1],
                      description=f"exponent applied to the normalised {short} curve of {table}")
        out.append(Candidate(f"relative_permeability:{phase}", "relative_permeability", p, (), (),
                             f"the {phase} relative permeability curve has another shape "
                             f"({short} in {table} rises earlier or later with saturation)",
                             1.0, PROBE["relative_permeability"],
                             {"phase": phase, "table": table}))
        p = Parameter(name=f"{short}_scale", kind="relperm", keywords=(table,), item=2,
                      mode="scale", low=RELPERM_SCALE_BOUNDS[0], high=RELPERM_SCALE_BOUNDS[1],
                      description=f"factor on the {short} curve of {table} (capped at 1)")
        out.append(Candidate(f"relative_permeability:{phase}:scale", "relative_permeability", p,
                             (), (), f"the {phase} relative permeability is higher or lower "
                             f"than the model says over the whole curve ({short} in {table} "
                             "times a factor, its shape kept)",
                             1.0, RELPERM_SCALE_PROBE, {"phase": phase, "table": table}))
        crit = "SWCR" if phase == "water" else "SGCR"
        room = critical_room(info, table)  # a shift below the table's first row does nothing
        low = max(RELPERM_ENDPOINT_BOUNDS[0], -room)
        p = Parameter(name=f"{short}_{crit.lower()}_shift", kind="relperm", keywords=(table,),
                      item=2, mode="endpoint", low=0.0 if low > -1e-3 else low,
                      high=RELPERM_ENDPOINT_BOUNDS[1],
                      description=f"shift of the critical saturation of the {short} curve of "
                                  f"{table} ({crit})")
        out.append(Candidate(f"relative_permeability:{phase}:endpoint", "relative_permeability",
                             p, (), (), f"the {phase} phase starts to flow at another saturation "
                             f"than the model says (the critical saturation of {short} in "
                             f"{table}, {crit}, moved; the curve's end points kept)",
                             0.0, RELPERM_ENDPOINT_PROBE,
                             {"phase": phase, "table": table,
                              "low_is_limit": low > RELPERM_ENDPOINT_BOUNDS[0]}))
    return out


def contact_depth(info: DeckInfo, space: ParameterSpace,
                  values: dict[str, float]) -> list[Candidate]:
    """The water-oil and the gas-oil contact, each where the deck's EQUIL gives one (a
    defaulted item, or a GOC above the reservoir's top that the datum sits at, still moves:
    the factor applies to the depth written)."""
    records = deck_blocks(info).get("EQUIL", [])
    out = []
    for item, short, contact in ((3, "woc", "water-oil"), (5, "goc", "gas-oil")):
        if not any(len(r) >= item and r[item - 1] != "1*" for r in records):
            continue
        p = Parameter(name=f"{short}_depth", kind="item_multiply", keywords=("EQUIL",),
                      item=item, low=CONTACT_BOUNDS[0], high=CONTACT_BOUNDS[1],
                      description=f"factor on the initial {contact} contact depth (EQUIL item "
                                  f"{item})")
        out.append(Candidate(f"contact_depth:{short}", "contact_depth", p, (), (),
                             f"the initial {contact} contact is deeper or shallower than the "
                             f"model says (EQUIL item {item})", 1.0, PROBE["contact_depth"],
                             {"contact": short, "item": item}))
    return out


def solution_gas(info: DeckInfo, space: ParameterSpace,
                 values: dict[str, float]) -> list[Candidate]:
    """The initial dissolved gas: RSVD's Rs column, else PBVD's bubble points."""
    names = info.keyword_names
    table = next((t for t in ("RSVD", "PBVD") if t in names), None)
    if table is None:
        return []
    what = "dissolved gas-oil ratio" if table == "RSVD" else "bubble point pressure"
    p = Parameter(name="rs_initial" if table == "RSVD" else "pb_initial",
                  kind="table_multiply", keywords=(table,), item=2,
                  low=SOLUTION_GAS_BOUNDS[0], high=SOLUTION_GAS_BOUNDS[1],
                  description=f"factor on the initial {what} ({table} item 2)")
    return [Candidate(f"solution_gas:{table.lower()}", "solution_gas", p, (), (),
                      f"the initial oil holds less dissolved gas than the model says (the "
                      f"{what} of {table}, a fluid property)", 1.0, PROBE["solution_gas"],
                      {"table": table})]


def critical_room(info: DeckInfo, table: str) -> float:
    """How far (saturation) the critical saturation of column 2 of ``table`` (SWOF / SWFN /
    SGOF / SGFN) can move down before it reaches the table's first row: the least over the
    deck's tables of that keyword (one per saturation region). 0 when a table starts at its
    critical saturation (a shift down then changes nothing); 0.5 when the tables cannot be
    read (defaulted items: the deck writer refuses to shift them anyway)."""
    rooms = []
    for rec in deck_blocks(info).get(table, []):
        try:
            t = np.array([float(x) for x in rec]).reshape(-1, width(table))
        except ValueError:
            return 0.5
        sat, kr = t[:, 0], t[:, 1]
        first = sat[0] if kr[-1] >= kr[0] else sat[-1]
        rooms.append(abs(critical_saturation(sat, kr) - float(first)))
    return min(rooms) if rooms else 0.5


def productivity_change(info: DeckInfo, space: ParameterSpace,
                        values: dict[str, float]) -> list[Candidate]:
    """None at build time: the ranking dates them (:func:`dated_productivity`)."""
    return []


def dated_productivity(info: DeckInfo, well: str, day: float) -> Candidate:
    """The candidate "``well``'s productivity index changed from report day ``day`` on": a
    ``WPIMULT`` factor (neutral 1) written in the schedule at that step."""
    date = (info.start + timedelta(days=day)).date().isoformat()
    p = Parameter(name=f"pi_{slug(well)}_from{day:g}".replace(".", "_"), kind="wpimult",
                  wells=(well,), low=PI_BOUNDS[0], high=PI_BOUNDS[1], start_day=day,
                  description=f"productivity multiplier of {well} from day {day:g}")
    return Candidate(f"productivity_change:{well}@{day:g}", "productivity_change", p, (well,), (),
                     f"the productivity of well {well} changed from day {day:g} ({date}) on: "
                     "damage, scale or a stimulation during the history, not a skin it always "
                     "had", 1.0, PROBE["productivity_change"],
                     {"start_day": day, "start_date": date})


FAMILIES = {"well_skin": well_skin, "regional_permeability": regional_permeability,
            "layer_permeability": layer_permeability,
            "vertical_permeability": vertical_permeability,
            "aquifer_strength": aquifer_strength,
            "fault_transmissibility": fault_transmissibility,
            "relative_permeability": relative_permeability,
            "productivity_change": productivity_change, "contact_depth": contact_depth,
            "solution_gas": solution_gas}


def build_candidates(info: DeckInfo, space: ParameterSpace, values: dict[str, float] | None = None,
                     kinds: tuple[str, ...] | list[str] | None = None) -> list[Candidate]:
    """Every candidate of the chosen families (default :data:`DEFAULT_KINDS`) for a deck and
    calibration space.

    ``values`` are the calibrated values of ``space`` (they set a well-skin candidate's neutral
    value). Parameter names never clash with the space's.
    """
    values = dict(values or {})
    out: list[Candidate] = []
    kinds = list(kinds or DEFAULT_KINDS)
    if "productivity_change" in kinds and "well_skin" not in kinds:
        kinds.insert(0, "well_skin")  # the date scan reads the well-skin probes
    for kind in kinds:
        if kind not in FAMILIES:
            raise ValueError(f"unknown extension kind {kind!r}; known: {list(KINDS)}")
        out.extend(FAMILIES[kind](info, space, values))
    taken = set(space.names)
    return [c for c in out if c.name not in taken]
