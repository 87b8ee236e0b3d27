"""Hidden effects the candidate library does not hold as they are: other geometry, another
mechanism of a known family, two effects at once, or no family at all.

The library searches a skin on one well, a box of +-3 cells centred on a well, a whole layer,
a full fault plane midway between well columns, a power law on krw / krg, an aquifer's
strength. A diagnosis that only finds effects drawn from that list proves little, so these
generators draw, from a seed (the relative-permeability family has a factor and a
critical-saturation shift on each curve, so ``relperm_scaling`` and ``relperm_endpoint`` ask
it to tell its own parameters apart - and the globals not to absorb them):

==================== ===================================================== ==================
generator            the truth hides                                        a right answer
==================== ===================================================== ==================
``partial_fault``    MULTX/MULTY on part of a plane (40-60 % of its        the library plane
                     length) between producers, off the library's midlines that parts the
                                                                            producers the
                                                                            same way
``offcentre_region`` a permeability box of 5x5, 7x7 or 9x9 columns         the regional family,
                     centred 3-4 cells off a well in both i and j (never    a box that mostly
                     one of the library's boxes, centred or moved)          coincides with it
``relperm_endpoint`` the water curve's critical saturation moved by        the relative-
                     +-0.05-0.10 (end-point scaling, not a shape change)    permeability family
``relperm_scaling``  the water or gas curve's relative permeability         the relative-
                     multiplied (x0.3-0.5 or x2-3, capped at 1), not        permeability family,
                     reshaped                                               that phase
``two_kinds``        two library effects of different kinds at once        both, each by kind
``contact``          the initial water-oil contact moved (EQUIL item 3,    ``unexplained``
                     +-0.3-0.8 % of its depth): no default family makes     (or none, when
                     that (``contact_depth`` does, when asked for)          invisible)
``pvt``              the initial oil's dissolved gas (RSVD item 2)         ``unexplained``
                     lowered by 7-15 %: the oil starts undersaturated,     (a fluid property:
                     its GOR lower until the pressure reaches the new      no default family
                     bubble point (``solution_gas`` when asked for)        acts on PVT)
``dated_productivity`` one producer's productivity index multiplied from a  the productivity-
                     report date in 20-50 % of the schedule on (WPIMULT    change family, that
                     x0.15-0.35 or x3-6: damage or a stimulation)           well, its start
                                                                            date within 92 days
``late_productivity`` the same from 77-85 % of the schedule on: after a      the same, named on
                     fitted window of 75 % of the record, so only a         a later window
                     later window holds it
``permeability_trend`` PERMX and PERMY x1/f at one edge of the grid to x f   ``unexplained``
                     at the other (f 2-4), log-linear along a horizontal    (or none, when
                     direction drawn uniformly: no family makes a smooth    invisible)
                     field-wide gradient
``completion_change`` one producer recompleted from a report date in 30-60 % ``unexplained``, or
                     of the schedule on: its connections shut, 1 to as      the productivity-
                     many new ones opened in the layers just above or       change family at
                     below them, in the initial oil column (a workover      that well, its start
                     in other layers)                                       within 92 days
==================== ===================================================== ==================

Each effect is a :class:`hmcore.scenarios.effects.HiddenEffect` whose candidate's ``kind`` is the
family a right answer names (``unexplained`` for no family) and whose ``details`` say which
generator made it and what a right answer must also name (``expect_wells``; ``expect_ids``:
the candidates that count, where the family has several that would not; a region: a box that
mostly coincides with the truth's, :func:`hmcore.scenarios.hidden.boxes_agree`;
``expect_kinds``: another family whose cause names the effect too, with those wells and the
start date, :func:`hmcore.scenarios.judge.names`). Strengths are
drawn from the fixed ranges above, not scaled to each deck's noise: most draws show a few times
above it, some do not (an end point the globals absorb, a small box far from the wells). Each
draw's signal is measured when its case is written (:func:`hmcore.scenarios.hidden.effect_signal`)
and one the fitted history hardly shows is judged as invisible, where ``none`` is right. Pure:
nothing here simulates; :func:`hmcore.scenarios.hidden.write_hidden_synthetic_case` and
``write_hidden_deck_case`` run the truth.
"""

from __future__ import annotations

import math
from itertools import takewhile

import numpy as np

from hmcore.diagnosis.candidate import (
    FAULT_BOUNDS,
    KINDS,
    PERM_BOUNDS,
    Candidate,
    well_column,
    wells_below,
)
from hmcore.diagnosis.extensions import (
    build_candidates,
    critical_room,
    dated_productivity,
    shifted_regions,
)
from hmcore.eclipse.deck_info import DeckInfo
from hmcore.errors import CaseError
from hmcore.model.deck_values import deck_blocks
from hmcore.model.parameters import Parameter, ParameterSpace
from hmcore.model.run_deck import edits_for, render_deck, trend_factors
from hmcore.ordering import natural_key
from hmcore.scenarios.effects import HiddenEffect, draw_library_effect

GENERATORS = ("partial_fault", "offcentre_region", "relperm_endpoint", "two_kinds", "contact",
              "dated_productivity", "late_productivity", "pvt", "relperm_scaling",
              "permeability_trend", "completion_change")
"""The generators. Each one's rng is seeded with its index here, so a new one goes at the end:
every other one then draws what it drew before."""
START_TOLERANCE_DAYS = 92.0
"""A dated cause names a dated effect when its start is this close (about a quarter)."""
TWO_KINDS_FROM = ("well_skin", "regional_permeability", "layer_permeability",
                  "aquifer_strength", "fault_transmissibility")
"""The kinds ``two_kinds`` draws its pair from (those every test deck offers)."""


def draw_effect(kind: str, seed: int, info: DeckInfo, space: ParameterSpace,
                values: dict[str, float], choices: list[str] | None = None) -> HiddenEffect:
    """A random candidate of library ``kind`` (optionally among ids ``choices``) and strength; a
    ``productivity_change`` is dated, so it is drawn as by the ``dated_productivity`` generator."""
    if kind == "productivity_change":
        return generate("dated_productivity", seed, info, space, values)[0]
    return draw_library_effect(kind, seed, info, space, values, choices)


def draw_effects(kind: str, seed: int, info: DeckInfo, space: ParameterSpace,
                 values: dict[str, float]) -> list[HiddenEffect]:
    """The effects of ``kind``: a library kind (one candidate, :func:`draw_effect`) or a
    generator's."""
    if kind in GENERATORS:
        return generate(kind, seed, info, space, values)
    return [draw_effect(kind, seed, info, space, values)]


def generate(name: str, seed: int, info: DeckInfo, space: ParameterSpace,
             values: dict[str, float]) -> list[HiddenEffect]:
    """The hidden effects of generator ``name`` for ``seed`` on the deck ``info`` (the
    calibration ``space`` at ``values``). ValueError for an unknown name or a deck that cannot
    carry it."""
    if name not in GENERATORS:
        raise ValueError(f"unknown generator {name!r}; the generators are {list(GENERATORS)} "
                         f"(and the library kinds {list(KINDS)})")
    rng = np.random.default_rng([seed, 101, GENERATORS.index(name)])
    if name == "two_kinds":
        offered = [k for k in TWO_KINDS_FROM if build_candidates(info, space, values, (k,))]
        if len(offered) < 2:
            raise ValueError(f"the deck {info.path} offers fewer than two of {TWO_KINDS_FROM}")
        a, b = rng.choice(len(offered), size=2, replace=False)
        return [draw_library_effect(offered[int(k)], seed, info, space, values)
                for k in (a, b)]
    c, value = {"partial_fault": _partial_fault, "offcentre_region": _offcentre_region,
                "relperm_endpoint": _relperm_endpoint,
                "relperm_scaling": lambda r, i, s: _relperm_scaling(r, i, s, seed),
                "contact": _contact, "pvt": _pvt,
                "dated_productivity": _dated_productivity,
                "late_productivity": _late_productivity,
                "permeability_trend": _permeability_trend,
                "completion_change": _completion_change}[name](rng, info, space)
    return [HiddenEffect(c, value)]


def _log_uniform(rng, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _partial_fault(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    nx, ny, nz = info.dims
    cols = [well_column(info, w) for w in info.producers]
    choices = []
    for axis, keyword in (("i", "MULTX"), ("j", "MULTY")):
        library = {c.parameter.box[0] if axis == "i" else c.parameter.box[2]: c.id
                   for c in build_candidates(info, space, {}, ("fault_transmissibility",))
                   if c.parameter.keywords == (keyword,)}
        pos = [c[0] if axis == "i" else c[1] for c in cols]
        # planes with producers on both sides (a barrier between wells), off the midlines;
        # a right answer is the library plane that parts the producers the same way
        for p in range(min(pos), max(pos)):
            same = [cid for q, cid in library.items()
                    if wells_below(info, axis, q) == wells_below(info, axis, p)]
            if p not in library and same:
                choices.append((axis, keyword, p, same))
    if not choices:
        raise ValueError(f"the deck {info.path} has no plane between producers off the "
                         "library's midlines for a partial fault")
    axis, keyword, p0, same = choices[int(rng.integers(len(choices)))]
    n_along = ny if axis == "i" else nx
    length = max(2, int(round(rng.uniform(0.4, 0.6) * n_along)))
    start = int(rng.integers(1, n_along - length + 2))
    span = (start, start + length - 1)
    box = (p0, p0, *span, 1, nz) if axis == "i" else (*span, p0, p0, 1, nz)
    p = Parameter(name=f"hidden_fault_{axis}{p0}", kind="multiply", keywords=(keyword,),
                  box=box, low=FAULT_BOUNDS[0], high=FAULT_BOUNDS[1],
                  description=f"{keyword} on part of the plane {axis} = {p0} | {p0 + 1}")
    other = "j" if axis == "i" else "i"
    c = Candidate(f"partial_fault:{axis}{p0}:{other}{span[0]}-{span[1]}",
                  "fault_transmissibility", p, (), (),
                  f"a sealing fault on the plane {axis} = {p0} | {p0 + 1}, over {other} = "
                  f"{span[0]}-{span[1]} only (off the library's midline planes)",
                  details={"generated": "partial_fault", "expect_wells": [],
                           "expect_ids": sorted(same)})
    return c, _log_uniform(rng, 1e-3, 1e-2)


def _offcentre_region(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    nx, ny, nz = info.dims
    wells = sorted(info.producers, key=natural_key)
    well = wells[int(rng.integers(len(wells)))]
    i, j = well_column(info, well)
    # the library's boxes: centred on each producer, and those moved beside it; the truth is
    # none of them (another size, or another place)
    library = {tuple(c.parameter.box) for c in build_candidates(
        info, space, None, ("regional_permeability",))}
    library |= {tuple(c.parameter.box) for w in wells for c in shifted_regions(info, w)}
    for _ in range(50):
        h = int(rng.integers(2, 5))  # a box of 5x5, 7x7 or 9x9 columns

        def shifted(x: int, n: int) -> int:
            """x moved 3-4 cells, towards the side with room for the box."""
            d = int(rng.integers(3, 5))
            up, down = x + d, x - d
            if up <= n - h and (down < h + 1 or rng.random() < 0.5):
                return up
            return down if down >= h + 1 else int(np.clip(up, h + 1, n - h))

        ci, cj = shifted(i, nx), shifted(j, ny)
        box = (ci - h, ci + h, cj - h, cj + h, 1, nz)
        if box not in library:
            break
    else:
        raise ValueError(f"the deck {info.path} leaves no room beside {well} for a box that "
                         "is not one of the library's")
    inside = [w for w in wells if w != well and box[0] <= well_column(info, w)[0] <= box[1]
              and box[2] <= well_column(info, w)[1] <= box[3]]
    lo, hi = (0.15, 0.35) if rng.random() < 0.6 else (3.0, 6.0)
    p = Parameter(name=f"hidden_region_{ci}_{cj}", kind="multiply", keywords=("PERMX", "PERMY"),
                  box=box, low=PERM_BOUNDS[0], high=PERM_BOUNDS[1],
                  description=f"PERMX and PERMY multiplier of cells i {box[0]}-{box[1]}, "
                              f"j {box[2]}-{box[3]}")
    c = Candidate(f"offcentre_region:{well}:i{box[0]}-{box[1]}:j{box[2]}-{box[3]}",
                  "regional_permeability", p, (well,), (),
                  f"the rock of cells i {box[0]}-{box[1]}, j {box[2]}-{box[3]} is more or less "
                  f"permeable: a box beside {well}, not centred on it"
                  + (f" ({', '.join(inside)} inside it)" if inside else ""),
                  details={"generated": "offcentre_region", "expect_wells": []})
    return c, _log_uniform(rng, lo, hi)


def _relperm_endpoint(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    table = next((t for t in ("SWOF", "SWFN") if t in info.keyword_names), None)
    if table is None:
        raise ValueError(f"the deck {info.path} has no SWOF or SWFN table to shift")
    shift = float(rng.uniform(0.05, 0.10)) * (1 if rng.random() < 0.5 else -1)
    if shift < 0 and not _rows_below_critical(info, table):
        shift = -shift  # the curve cannot start earlier than the table's first row
    p = Parameter(name="hidden_swcr_shift", kind="relperm", keywords=(table,), item=2,
                  mode="endpoint", low=-0.2, high=0.2,
                  description=f"critical water saturation of {table} moved")
    c = Candidate(f"relperm_endpoint:water:{shift:+.3f}", "relative_permeability", p, (), (),
                  f"the water relative permeability starts at another saturation (SWCR "
                  f"{shift:+.3f}): an end point, not the curve's shape",
                  details={"generated": "relperm_endpoint", "expect_wells": [],
                           "expect_ids": ["relative_permeability:water",
                                          "relative_permeability:water:scale",
                                          "relative_permeability:water:endpoint"]})
    return c, shift


def _relperm_scaling(rng, info: DeckInfo, space: ParameterSpace,
                     seed: int) -> tuple[Candidate, float]:
    """The water or the gas curve (of those the deck has) multiplied, its shape kept: the
    library reshapes the curves (a power law), it does not scale them. The phase takes turns
    with the seed (stratified: any two consecutive seeds scale both curves of a deck that has
    both); the strength is drawn."""
    phases = [(c.details["phase"], c.details["table"]) for c in build_candidates(
        info, space, {}, ("relative_permeability",)) if c.parameter.mode == "power"]
    if not phases:
        raise ValueError(f"the deck {info.path} has no SWOF, SWFN, SGOF or SGFN table to scale")
    phase, table = phases[seed % len(phases)]
    short = "krw" if phase == "water" else "krg"
    lo, hi = (0.3, 0.5) if rng.random() < 0.6 else (2.0, 3.0)
    p = Parameter(name=f"hidden_{short}_scale", kind="relperm", keywords=(table,), item=2,
                  mode="scale", low=0.1, high=10.0,
                  description=f"{short} of {table} multiplied (capped at 1)")
    value = _log_uniform(rng, lo, hi)
    c = Candidate(f"relperm_scaling:{phase}:x{value:.3f}", "relative_permeability", p, (), (),
                  f"the {phase} relative permeability is {value:.2f} times the model's over "
                  f"the whole curve ({short} of {table}, capped at 1): a scale, not a shape",
                  details={"generated": "relperm_scaling", "expect_wells": [],
                           "expect_ids": [f"relative_permeability:{phase}",
                                          f"relative_permeability:{phase}:scale"]})
    return c, value


def _rows_below_critical(info: DeckInfo, table: str) -> bool:
    """Whether the first ``table`` (SWOF / SWFN) has rows below the critical water saturation,
    so that a negative end-point shift changes it (the synthetic deck's starts there: without
    such rows a negative shift is no effect at all)."""
    return critical_room(info, table) > 1e-3


def _contact(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    factor = 1.0 + float(rng.uniform(0.003, 0.008)) * (1 if rng.random() < 0.5 else -1)
    p = Parameter(name="hidden_woc_depth", kind="item_multiply", keywords=("EQUIL",), item=3,
                  low=0.95, high=1.05, description="water-oil contact depth (EQUIL item 3)")
    return _of_no_family(info, "contact", p, f"contact:woc:x{factor:.4f}",
                         f"the initial water-oil contact is "
                         f"{'deeper' if factor > 1 else 'shallower'} than the model says "
                         f"(depth x{factor:.4f})"), factor


def _pvt(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    """Less gas dissolved in the initial oil than the model says (RSVD x0.85-0.93): the
    produced GOR starts lower, and free gas appears later, on every producer. Unlike a moved
    contact, no candidate can mimic it: the library changes rock, wells, faults, aquifers and
    the saturation curves, never what the oil holds in solution."""
    factor = float(rng.uniform(0.85, 0.93))
    p = Parameter(name="hidden_rs_initial", kind="table_multiply", keywords=("RSVD",), item=2,
                  low=0.5, high=1.5, description="initial solution gas-oil ratio (RSVD item 2)")
    return _of_no_family(info, "pvt", p, f"pvt:rsvd:x{factor:.4f}",
                         f"the initial oil holds less dissolved gas than the model says (RSVD "
                         f"x{factor:.4f}): a fluid property"), factor


def _of_no_family(info: DeckInfo, generated: str, p: Parameter, cid: str,
                  says: str) -> Candidate:
    """The hidden candidate of an effect no family makes: a right answer is ``unexplained``."""
    if p.keywords[0] not in info.keyword_names:
        raise ValueError(f"the deck {info.path} has no {p.keywords[0]} keyword, which the "
                         f"{generated} generator changes ({p.description})")
    return Candidate(cid, "unexplained", p, (), (), says + ": no family of the library",
                     details={"generated": generated, "expect_wells": []})


def _dated_productivity(rng, info: DeckInfo, space: ParameterSpace,
                        span: tuple[float, float] = (0.2, 0.5),
                        generated: str = "dated_productivity") -> tuple[Candidate, float]:
    wells = sorted(info.producers, key=natural_key)
    well = wells[int(rng.integers(len(wells)))]
    end = info.end_days
    days = [d for d in info.report_days if span[0] * end <= d <= span[1] * end]
    if not days:
        raise ValueError(f"the deck {info.path} has no report step in "
                         f"{span[0]:.0%}-{span[1]:.0%} of its schedule to start a "
                         "productivity change at")
    day = float(days[int(rng.integers(len(days)))])
    lib = dated_productivity(info, well, day)
    c = Candidate(lib.id, lib.kind, lib.parameter, lib.wells, (), lib.description,
                  details={"generated": generated, "expect_wells": [well],
                           "start_day": day})
    lo, hi = (0.15, 0.35) if rng.random() < 0.6 else (3.0, 6.0)
    return c, _log_uniform(rng, lo, hi)


def _late_productivity(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    """A productivity change from 77-85 % of the schedule on: after a fitted window of 75 % of
    the record, so a diagnosis that stops at that window sees none of it in the history it
    fits, only in the held-back part: found only by a diagnosis that takes the longer record
    (its later window)."""
    return _dated_productivity(rng, info, space, (0.77, 0.85), "late_productivity")


TREND_FACTOR = (2.0, 4.0)
"""The range of a permeability trend's f (log-uniform): x1/f at one edge of the grid, x f at
the other, so the field's two ends differ 4-16 times."""


def _permeability_trend(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    """PERMX and PERMY multiplied by a factor that rises log-linearly across the whole grid
    along a horizontal direction drawn uniformly (:func:`hmcore.model.run_deck.trend_factors`),
    from x1/f at the farthest column behind to x f at the farthest ahead (f in
    :data:`TREND_FACTOR`): a facies or compaction trend the model's permeability lacks. No
    family makes it: the regional family changes a box and the layer family a whole layer,
    each by one factor, and the globals multiply the field uniformly (the trend's geometric mean
    over the grid's columns is 1, so they absorb little of it). A right answer is
    ``unexplained``; a box at a well on the trend's high or low side can mimic part of it,
    and is wrong: it says the rest of the field is as modelled."""
    angle = float(rng.uniform(0.0, 360.0))
    value = _log_uniform(rng, *TREND_FACTOR)
    p = Parameter(name="hidden_perm_trend", kind="trend", keywords=("PERMX", "PERMY"),
                  direction=angle, low=0.1, high=10.0,
                  description=f"PERMX and PERMY trend across the grid, rising towards "
                              f"{angle:.0f} degrees from +i (towards +j)")
    factors = trend_factors(info.dims, angle, value)
    at = ", ".join(f"{w} x{factors[well_column(info, w)]:.2f}"
                   for w in sorted(info.producers, key=natural_key)
                   if info.wells[w].connections)  # a producer never completed: no column
    return _of_no_family(info, "permeability_trend", p,
                         f"permeability_trend:{angle:.0f}deg:x{value:.3f}",
                         f"the permeability trends across the field, x{1 / value:.2f} at one "
                         f"edge to x{value:.2f} at the other, rising towards {angle:.0f} "
                         f"degrees from +i ({at})"), value


def _completion_change(rng, info: DeckInfo, space: ParameterSpace) -> tuple[Candidate, float]:
    """One producer recompleted mid-history, as a workover would: from a report day in 30-60 %
    of the schedule on, every connection it has is shut and 1 to as many new ones as it had
    are opened in the layers just above its top connection or just below its bottom one, in
    its column (a vertical well, open in some layers only), each of them in the initial oil
    column (:func:`_oil_layers`: no workover perforates only the gas cap or the aquifer, and a
    well that can flow no oil is shut by the simulator, its history no longer a well's). The
    value, the new connections' productivity multiplier, is 1: perforated as the model
    computes connection factors, so the strength is the move itself.

    A right answer is ``unexplained``, or the productivity-change family at that well starting
    within :data:`START_TOLERANCE_DAYS` of the day (``expect_kinds``; accepted, so the held-back
    misfit drops). Why the second is fair too: the well's productivity index does change at that
    date (the new layers have another kh), so a dated productivity change names where and when,
    which is what sends an engineer to the well's workover record; it cannot say what, since
    other layers bring other water and gas (a deeper completion cones water sooner, a shallower
    one gas), which no PI factor reproduces - so it counts only as that family, at that well
    and date, and any other family (a skin the well always had, a region, a layer's
    permeability) or another well or date is wrong."""
    nz = info.dims[2]
    oil = _oil_layers(info)
    options = []
    for well in sorted(info.producers, key=natural_key):
        conns = info.wells[well].connections
        ks = sorted({k for _, _, k in conns})
        if len({(i, j) for i, j, _ in conns}) != 1 or not oil.get(well):
            continue  # not a vertical well: its layers are no interval to move
        up = list(takewhile(lambda k: k in oil[well], range(ks[0] - 1, 0, -1)))[::-1]
        down = list(takewhile(lambda k: k in oil[well], range(ks[-1] + 1, nz + 1)))
        if up or down:
            options.append((well, ks, [side for side in (up, down) if side]))
    if not options:
        raise ValueError(f"the deck {info.path} has no vertical producer with oil-bearing "
                         "layers just above or below its connections to recomplete in")
    end = info.end_days
    days = [d for d in info.report_days if 0.3 * end <= d <= 0.6 * end]
    if not days:
        raise ValueError(f"the deck {info.path} has no report step in 30%-60% of its schedule "
                         "to recomplete a well at")
    day = float(days[int(rng.integers(len(days)))])
    for o in rng.permutation(len(options)):  # the first well the schedule lets be recompleted
        well, ks, sides = options[int(o)]
        side = sides[int(rng.integers(len(sides)))]
        n = int(rng.integers(1, min(len(ks), len(side)) + 1))
        layers = tuple(side[-n:] if side[0] < ks[0] else side[:n])  # next to the old ones
        p = Parameter(name=f"hidden_recompletion_{well}".replace("-", "_"), kind="recomplete",
                      wells=(well,), layers=layers, start_day=day, low=0.1, high=10.0,
                      description=f"{well} recompleted in layer(s) {_span(layers)} from day "
                                  f"{day:g}")
        try:  # completed by the day, and no later COMPDAT of the well that would undo it
            render_deck(info, edits_for(ParameterSpace(parameters=(p,)), {p.name: 1.0}, info))
        except CaseError:
            continue
        break
    else:
        raise ValueError(f"the deck {info.path} has no producer its schedule lets be "
                         f"recompleted at day {day:g}")
    span = _span
    c = Candidate(f"completion_change:{well}:k{span(ks)}>k{span(layers)}@{day:g}",
                  "unexplained", p, (well,), layers,
                  f"well {well} was recompleted from day {day:g} on: its connections in "
                  f"layer(s) {span(ks)} shut, layer(s) {span(layers)} opened "
                  f"({'shallower' if layers[0] < ks[0] else 'deeper'}): no family of the "
                  "library moves a well's completions",
                  details={"generated": "completion_change", "expect_wells": [well],
                           "start_day": day, "expect_kinds": ["productivity_change"]})
    return c, 1.0


DEPTH_TO_METRES = {"METRIC": 1.0, "PVT-M": 1.0, "FIELD": 0.3048, "LAB": 0.01}
"""A deck's depth unit (EQUIL's contacts as written) in metres, OPM's unit of cell depths."""


def _span(layers) -> str:
    return f"{layers[0]}-{layers[-1]}" if len(layers) > 1 else f"{layers[0]}"


def _oil_layers(info: DeckInfo) -> dict[str, set[int]]:
    """Per producer, the layers of its column whose cell centre lies in the initial oil column:
    below the gas-oil contact and above the water-oil contact of the deck's EQUIL (items 5 and
    3; with several records, the deepest gas-oil and the shallowest water-oil contact; a
    defaulted one bounds nothing). The grid's cell depths are OPM's (the deck parsed again)."""
    records = deck_blocks(info).get("EQUIL") or []
    metres = DEPTH_TO_METRES.get(info.unit_system, 1.0)  # OPM's cell depths are in metres
    contact = [[float(r[k]) * metres for r in records if len(r) > k and r[k] != "1*"]
               for k in (4, 2)]
    goc = max(contact[0], default=-math.inf)
    woc = min(contact[1], default=math.inf)
    grid = DeckInfo.inspect_parsed(info.path)[1].state.grid()
    out = {}
    for well in info.producers:
        if not info.wells[well].connections:
            continue
        i, j, _ = info.wells[well].connections[0]
        out[well] = {k for k in range(1, info.dims[2] + 1)
                     if goc < grid.getCellDepth(i - 1, j - 1, k - 1) < woc}
    return out
