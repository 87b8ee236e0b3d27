"""The per-run deck's edits in the SCHEDULE section (:mod:`hmcore.model.run_deck` renders the
deck and calls these with its rendering ``state``):

* a productivity multiplier's ``WPIMULT`` after each COMPDAT that connects its wells, one record
  per connection (:func:`wpimult_block`);
* a dated one (``start_day``) and a recompletion (a workover that moves a well's connections to
  other layers) at the first report step at or after their day: the DATES or TSTEP block is
  split after that step and the recompletion's COMPDAT, then the WPIMULT, written there
  (:func:`dated_steps`).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path

from hmcore.eclipse.deck_info import DeckInfo
from hmcore.eclipse.lexer import Block, expand_repeats, records
from hmcore.errors import CaseError, Problem


@dataclass(frozen=True)
class PiMultiplier:
    """Multiply the productivity (injectivity) index of ``wells``' connections: a ``WPIMULT``
    record after every COMPDAT that (re)defines their connections; from ``start_day`` on when
    given (written at that report step, then after the COMPDATs that follow it)."""

    wells: tuple[str, ...]
    factor: float
    start_day: float | None = None


@dataclass(frozen=True)
class Recompletion:
    """``well`` recompleted from ``start_day`` on (a workover): at the first report step at or
    after that day a COMPDAT in the schedule shuts every connection the well has so far and
    opens one in each of ``layers`` in its column (its first connection's record with the other
    items kept: diameter, skin as edited), then a ``WPIMULT`` ``factor`` on the new connections
    (and the productivity multipliers in force, as after any COMPDAT)."""

    well: str
    layers: tuple[int, ...]
    factor: float
    start_day: float


def format_compdat_record(tokens: list[str]) -> str:
    """One COMPDAT (or other list keyword's) record of ``tokens``, a line of the deck."""
    return " " + " ".join(tokens) + " /\n"


def wpimult_block(compdat: Block, pimults: list[PiMultiplier], applied: set) -> str:
    """WPIMULT for the connections this COMPDAT block defines for the targeted wells: one
    record per connection (well, I, J, K), so a connection defined once gets the factor once,
    whatever other COMPDAT keywords the well has (a whole-well WPIMULT after each would
    compound on the connections defined before). ``applied`` collects the wells reached."""
    lines = []
    for rec in records(compdat.body):
        items = expand_repeats(rec)
        if not items:
            continue
        name = items[0].strip("'\"")
        coords = [_int_or_none(x) for x in items[1:5]] + [None] * (4 - len(items[1:5]))
        i, j, k1, k2 = coords
        for m in pimults:
            for well in m.wells:
                if not fnmatch.fnmatchcase(well, name):
                    continue
                applied.add(well)
                if k1 is None:
                    lines.append(f" '{well}' {m.factor:.10g} /\n")
                    continue
                ij = f"{i if i else '1*'} {j if j else '1*'}"
                lines += [f" '{well}' {m.factor:.10g} {ij} {k} /\n"
                          for k in range(k1, (k2 or k1) + 1)]
    return ("\n-- productivity multipliers added by hmflow (one record per connection)\n"
            "WPIMULT\n" + "".join(lines) + "/\n\n") if lines else ""


def keep_connections(compdat: Block, file: Path, state: dict) -> None:
    """Keep the connection records of ``compdat`` as written (``state["connections"]``), which
    a recompletion shuts; refuse one that names a well already recompleted (it would undo the
    move)."""
    for rec in records(compdat.body):
        items = expand_repeats(rec)
        name = items[0].strip("'\"") if items else ""
        moved = [m.well for m in state["moved"] if fnmatch.fnmatchcase(m.well, name)]
        if moved:
            raise CaseError([Problem(str(file), f"a COMPDAT after the recompletion of {moved[0]} "
                                     "redefines its connections, which would undo the move",
                                     "recomplete a well the schedule completes once")])
        state["connections"].append(items)


def _recompletion(m: Recompletion, day: float, info: DeckInfo, state: dict) -> str:
    """The COMPDAT of the recompletion ``m`` at report day ``day`` (every connection of the
    well so far shut, one opened per layer, from the well's first record), then the WPIMULT of
    the multipliers in force and of ``m.factor`` on the new connections."""
    old = [x + ["1*"] * (6 - len(x)) for x in state["connections"]
           if fnmatch.fnmatchcase(m.well, x[0].strip("'\""))]
    if not old:
        raise CaseError([Problem(str(info.path), f"no COMPDAT connects {m.well} before day "
                                 f"{day:g}, so it cannot be recompleted there",
                                 "recomplete a well the schedule has completed by then")])
    name = f"'{m.well}'"
    shut = [[name, *x[1:5], "'SHUT'", *x[6:]] for x in old]
    # the new layers' connection factor and kh (items 8 and 10) are the simulator's to compute:
    # the old layer's would carry over otherwise (a deck that writes them, as exports do)
    tail = ["1*" if n in (7, 9) else v for n, v in enumerate(old[0][6:], start=6)]
    new = [[name, *old[0][1:3], str(k), str(k), "'OPEN'", *tail] for k in m.layers]
    opened = Block("COMPDAT", ["COMPDAT\n", *map(format_compdat_record, new), "/\n"])
    active = [p for p in state["pimults"] if p.start_day is None or p in state["dated"]]
    own = [PiMultiplier((m.well,), m.factor)] if m.factor != 1.0 else []
    state["connections"].extend(shut + new)
    state["moved"].append(m)
    return (f"-- {m.well} recompleted in layer(s) {', '.join(map(str, m.layers))} from day "
            f"{day:g} by hmflow: its connections so far shut\nCOMPDAT\n"
            + "".join(map(format_compdat_record, shut + new)) + "/\n\n"
            + wpimult_block(opened, active, state["pi_applied"])
            + wpimult_block(opened, own, set()))


def dated_steps(block: Block, info: DeckInfo, state: dict) -> str:
    """A DATES or TSTEP block, counted in report steps (``state["step"]``), split after the
    step that reaches a pending recompletion's or dated productivity multiplier's day, with
    its COMPDAT (:func:`_recompletion`) and then its WPIMULT there: one whole-well record per
    well completed so far (its connections defined so far, once; a well completed later gets
    the factor after its COMPDAT)."""
    if block.keyword == "DATES":
        units = [" " + " ".join(expand_repeats(r)) + " /\n" for r in records(block.body)]
    else:
        units = [x for r in records(block.body) for x in expand_repeats(r)]
    pieces: list[str] = []
    current: list[str] = []

    def flush() -> None:
        if current:
            body = ("".join(current) if block.keyword == "DATES"
                    else " " + " ".join(current) + " /\n")
            pieces.append(f"{block.keyword}\n{body}" + ("/\n\n" if block.keyword == "DATES"
                                                         else "\n"))
            current.clear()

    for unit in units:
        current.append(unit)
        state["step"] += 1
        day = info.report_days[min(state["step"], len(info.report_days) - 1)]
        due = [m for m in state["pimults"] if m.start_day is not None
               and m not in state["dated"] and day >= m.start_day - 1e-6]
        moves = [m for m in state["moves"] if m not in state["moved"]
                 and day >= m.start_day - 1e-6]
        if due or moves:
            flush()
            pieces += [_recompletion(m, day, info, state) for m in moves]
            lines = []
            for m in due:
                state["dated"].append(m)
                for well in m.wells:
                    if any(fnmatch.fnmatchcase(well, name) for name in state["completed"]):
                        state["pi_applied"].add(well)
                        lines.append(f" '{well}' {m.factor:.10g} /\n")
            if lines:
                pieces.append(f"-- productivity multipliers from day {day:g} added by hmflow\n"
                              "WPIMULT\n" + "".join(lines) + "/\n\n")
    if len(pieces) == 0:
        return "".join(block.lines)
    flush()
    return "".join(pieces)


def _int_or_none(token: str) -> int | None:
    try:
        value = int(float(token))
    except ValueError:  # '1*' defaults, quoted text
        return None
    return value if value > 0 else None
