"""Deck preparation: write a per-run deck with parameter edits into an isolated run directory.

The base deck is never modified. The per-run deck is a copy of the main file (and of any include
file that must change) with

* a ``MULTIPLY`` block inserted at the end of the GRID section, i.e. just before the next
  section keyword (``EDIT`` or ``PROPS``), so it acts after every grid property and after
  ``COPY PERMX PERMY``;
* ``MULTIREG``, ``MULTFLT`` and ``MULTREGT`` blocks there too for region, fault and
  between-region multipliers;
* ``WPIMULT`` after every COMPDAT that connects a well with a productivity multiplier; a dated
  one (``start_day``) in the schedule at the first report step at or after its day (a DATES or
  TSTEP keyword is split there), then after the COMPDATs that follow;
* COMPDAT item 11 (skin) rewritten for the targeted wells (and layers);
* a permeability trend (kind ``trend``) as one boxed ``MULTIPLY`` record per column;
* a recompletion (kind ``recomplete``) as a COMPDAT in the schedule at its report step (the
  schedule's edits are in :mod:`hmcore.model.schedule_edits`);
* every ``INCLUDE`` path made absolute (unchanged include files are not copied).

Keywords are located by a small Eclipse lexer (comments, quotes, ``N*`` repeats, ``/``
terminators) restricted to the keywords OPM's parser found in the deck, never by line numbers.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass
from pathlib import Path

from hmcore.eclipse.deck_info import SECTION_NAMES as SECTIONS
from hmcore.eclipse.deck_info import DeckInfo
from hmcore.eclipse.includes import resolve_include
from hmcore.eclipse.lexer import (
    Block,
    expand_repeats,
    include_target,
    records,
    split_blocks,
    tokenize,
)
from hmcore.eclipse.tables import width as table_width
from hmcore.errors import CaseError, Problem
from hmcore.model.parameters import MULTIREG_REGIONS, Parameter, ParameterSpace
from hmcore.model.schedule_edits import (
    PiMultiplier,
    Recompletion,
    dated_steps,
    format_compdat_record,
    keep_connections,
    wpimult_block,
)

_COMPDAT_SKIN_ITEM = 11


# ----------------------------------------------------------------------------- edits
@dataclass(frozen=True)
class Multiply:
    """Multiply grid keyword ``keyword`` by ``factor`` (in a 1-based box when given)."""

    keyword: str
    factor: float
    box: tuple[int, int, int, int, int, int] | None = None
    region: tuple[str, tuple[int, ...]] | None = None  # (MULTNUM/FLUXNUM/OPERNUM, numbers)

    def region_records(self) -> str:
        """MULTIREG records: one per region number."""
        keyword, numbers = self.region
        flag = MULTIREG_REGIONS[keyword.upper()]
        return "".join(f" '{self.keyword}' {self.factor:.10g} {n} '{flag}' /\n" for n in numbers)

    def record(self) -> str:
        box = " ".join(str(b) for b in self.box) if self.box else ""
        return f" '{self.keyword}' {self.factor:.10g} {box} /".replace("  /", " /")


@dataclass(frozen=True)
class SetSkin:
    """Set the skin (COMPDAT item 11) of ``wells``' connections, in ``layers`` when given."""

    wells: tuple[str, ...]
    skin: float
    layers: tuple[int, ...] = ()


@dataclass(frozen=True)
class ItemMultiply:
    """Multiply item ``item`` (1-based) of ``keyword``'s records (first item == ``match``)."""

    keyword: str
    item: int
    factor: float
    match: str | None = None


@dataclass(frozen=True)
class RegionTransmissibility:
    """Multiply the transmissibility between two regions (``MULTREGT``, every direction)."""

    regions: tuple[int, int]
    factor: float
    region: str = "MULTNUM"

    def record(self) -> str:
        r1, r2 = self.regions
        return (f" {r1} {r2} {self.factor:.10g} 'XYZ' 'ALL' "
                f"'{MULTIREG_REGIONS[self.region.upper()]}' /\n")


@dataclass(frozen=True)
class FaultMultiplier:
    """Set the transmissibility multiplier of the named faults (``MULTFLT`` at the end of
    GRID; OPM and Eclipse take the last value given for a fault, replacing the deck's own)."""

    faults: tuple[str, ...]
    factor: float

    def records(self) -> str:
        return "".join(f" '{f}' {self.factor:.10g} /\n" for f in self.faults)


@dataclass(frozen=True)
class TableTransform:
    """Scale (``mode="scale"``, capped at 1), reshape (``mode="power"``), move the critical
    saturation of (``mode="endpoint"``) or multiply (``mode="multiply"``, a fluid table)
    column ``column`` of tables."""

    keyword: str
    column: int
    mode: str
    value: float


Edit = (Multiply | SetSkin | ItemMultiply | TableTransform | FaultMultiplier
        | RegionTransmissibility | PiMultiplier | Recompletion)
GRID_END = (Multiply, FaultMultiplier, RegionTransmissibility)  # written at the end of GRID


def edits_for(space: ParameterSpace, values: dict[str, float], info: DeckInfo) -> list[Edit]:
    """Deck edits for the parameter values given (parameters not in ``values`` are untouched)."""
    unknown = [n for n in values if n not in space.names]
    if unknown:
        raise KeyError(f"unknown parameter(s) {unknown}; this case has {space.names}")
    edits: list[Edit] = []
    for p in space.parameters:
        if p.name in values:
            edits.extend(_parameter_edits(p, float(values[p.name]), info))
    return edits


def _parameter_edits(p: Parameter, value: float, info: DeckInfo) -> list[Edit]:
    if p.kind == "multiply":
        region = (p.region.upper(), tuple(p.region_numbers)) if p.region else None
        return [Multiply(k.upper(), value, p.box, region) for k in p.keywords]
    if p.kind == "multregt":
        return [RegionTransmissibility(tuple(p.region_numbers), value, p.region or "MULTNUM")]
    if p.kind == "item_multiply":
        return [ItemMultiply(p.keywords[0].upper(), int(p.item), value, p.match)]
    if p.kind == "relperm":
        return [TableTransform(p.keywords[0].upper(), int(p.item or 2), p.mode, value)]
    if p.kind == "table_multiply":
        return [TableTransform(p.keywords[0].upper(), int(p.item), "multiply", value)]
    if p.kind == "fault":
        return [FaultMultiplier(tuple(p.faults), value)]
    if p.kind == "wpimult":
        return [PiMultiplier(tuple(p.wells or info.producers), value, p.start_day)]
    if p.kind == "latent":  # the fields it makes are the run's (LatentSimulator), not the deck's
        return []
    if p.kind == "trend":
        nz = info.dims[2]
        return [Multiply(k.upper(), f, (i, i, j, j, 1, nz)) for k in p.keywords
                for (i, j), f in trend_factors(info.dims, float(p.direction), value).items()]
    if p.kind == "recomplete":
        return [Recompletion(p.wells[0], tuple(p.layers), value, float(p.start_day))]
    wells = p.wells or tuple(info.producers)
    return [SetSkin(tuple(wells), value, p.layers)]


def trend_factors(dims: tuple[int, int, int], direction: float,
                  value: float) -> dict[tuple[int, int], float]:
    """The factor of each column (i, j), 1-based, of a trend across the grid ``dims``:
    ``value ** s``, where s is the column's position along the horizontal ``direction``
    (degrees from +i towards +j) from the grid's centre, -1 at the farthest column behind it
    and 1 at the farthest ahead: x1/value at one edge to x value at the other, linear in log."""
    nx, ny = dims[0], dims[1]
    c, s = math.cos(math.radians(direction)), math.sin(math.radians(direction))
    along = {(i, j): (i - (nx + 1) / 2) * c + (j - (ny + 1) / 2) * s
             for i in range(1, nx + 1) for j in range(1, ny + 1)}
    reach = max(max(abs(u) for u in along.values()), 1e-12)
    return {ij: value ** (u / reach) for ij, u in along.items()}


# ----------------------------------------------------------------------------- rendering
def _rewrite_compdat(block: Block, skins: list[SetSkin], file: Path) -> Block:
    """COMPDAT with item 11 replaced for targeted connections; untouched records kept as text."""
    new_lines = [block.lines[0], "-- records rewritten by hmflow (skin, item 11)\n"]
    for rec in records(block.body):
        items = expand_repeats(rec)
        well = items[0].strip("'\"")
        pieces = [items]
        for edit in skins:
            if well in edit.wells:
                pieces = [_set_skin(p, edit) for p in _split_layers(pieces, edit.layers)]
                pieces = [x for sub in pieces for x in sub]
            elif any(ch in well for ch in "*?") and any(fnmatch.fnmatch(w, well) for w in edit.wells):
                raise CaseError([Problem(str(file), f"COMPDAT uses the well template '{well}', "
                                         "which hmflow cannot split per well",
                                         "list each well's connections explicitly")])
        for p in pieces:
            new_lines.append(format_compdat_record(p))
    new_lines.append("/\n\n")
    return Block("COMPDAT", new_lines)


def _split_layers(pieces: list[list[str]], layers: tuple[int, ...]) -> list[list[str]]:
    if not layers:
        return pieces
    out = []
    for items in pieces:
        k1, k2 = int(items[3]), int(items[4])
        if k1 == k2 or not any(k1 <= k <= k2 for k in layers):
            out.append(items)
            continue
        for k in range(k1, k2 + 1):
            single = list(items)
            single[3] = single[4] = str(k)
            out.append(single)
    return out


def _set_skin(items: list[str], edit: SetSkin) -> list[list[str]]:
    if edit.layers:
        k1, k2 = int(items[3]), int(items[4])
        if not (k1 == k2 and k1 in edit.layers):
            return [items]
    padded = items + ["1*"] * (_COMPDAT_SKIN_ITEM - len(items))
    padded[_COMPDAT_SKIN_ITEM - 1] = f"{edit.skin:.10g}"
    return [padded]


def _rewrite_items(block: Block, edits: list[ItemMultiply], file: Path) -> Block:
    """Records of ``block.keyword`` with the targeted numeric items multiplied."""
    new_lines = [block.lines[0], "-- records rewritten by hmflow (item multipliers)\n"]
    for rec in records(block.body):
        items = expand_repeats(rec)
        for e in edits:
            if e.match is not None and items[0].strip("'\"") != e.match:
                continue
            if len(items) < e.item or items[e.item - 1] == "1*":
                raise CaseError([Problem(str(file), f"{e.keyword} item {e.item} is defaulted in "
                                         f"record {' '.join(rec)}; hmflow cannot multiply a default",
                                         f"write the value of item {e.item} explicitly")])
            items[e.item - 1] = f"{float(items[e.item - 1]) * e.factor:.10g}"
        new_lines.append(format_compdat_record(items))
    new_lines.append("/\n\n")
    return Block(block.keyword, new_lines)


def _rewrite_tables(block: Block, edits: list[TableTransform], file: Path) -> Block:
    """Tables of ``block.keyword`` (saturation or fluid) with one column transformed."""
    import numpy as np

    ncol = table_width(block.keyword)
    new_lines = [block.lines[0], "-- tables rewritten by hmflow\n"]
    for rec in _table_records(block.body):
        values = np.array([float(x) for x in expand_repeats(rec)], dtype=float)
        if values.size % ncol:
            raise CaseError([Problem(str(file), f"{block.keyword} table has {values.size} numbers, "
                                     f"not a multiple of {ncol} columns (defaults are not supported)",
                                     "write every table value explicitly")])
        table = values.reshape(-1, ncol)
        for e in edits:
            col = table[:, e.column - 1]
            top = col.max()
            if e.mode == "multiply":
                col = col * e.value
            elif e.mode == "scale":
                col = np.minimum(col * e.value, 1.0)
            elif e.mode == "endpoint":
                col = shift_endpoint(table[:, 0], col, e.value)
            elif top > 0:
                col = top * (col / top) ** e.value
            table[:, e.column - 1] = col
        new_lines += [" " + " ".join(f"{v:.8g}" for v in row) + "\n" for row in table]
        new_lines.append("/\n")
    new_lines.append("\n")
    return Block(block.keyword, new_lines)


def critical_saturation(sat, kr) -> float:
    """Where ``kr`` on the saturation nodes ``sat`` leaves 0: the last zero before it rises (or,
    for a falling curve, the first zero after it falls); its first node when it has no zero."""
    import numpy as np

    sat, kr = np.asarray(sat, float), np.asarray(kr, float)
    s, k = (sat, kr) if kr[-1] >= kr[0] else (sat[::-1], kr[::-1])
    zero = np.flatnonzero(k <= 0)
    return float(s[zero[-1]] if zero.size and zero[-1] < k.size - 1 else s[0])


def shift_endpoint(sat, kr, shift: float):
    """``kr`` on the saturation nodes ``sat`` with its critical saturation moved by ``shift``.

    The critical saturation is where the curve leaves 0 (the last zero before it rises, or the
    first zero after it falls); the curve between it and its far end point (the table's last
    or first node) is stretched linearly onto the new range and read at the same nodes, so the
    table keeps its rows (TABDIMS) and its end points."""
    import numpy as np

    sat, kr = np.asarray(sat, float), np.asarray(kr, float)
    if shift == 0:
        return kr.copy()  # a curve with no zero row would otherwise lose its first value
    rising = kr[-1] >= kr[0]
    s, k = (sat, kr) if rising else (sat[::-1], kr[::-1])
    sign = 1.0 if rising else -1.0
    crit = critical_saturation(sat, kr)
    far = s[-1]
    span = far - crit
    if abs(span) < 1e-12:
        return kr.copy()
    new_crit = np.clip(crit + sign * shift, min(s[0], far), max(s[0], far))
    new_crit = crit + np.clip(new_crit - crit, -0.98 * span if sign > 0 else 0.98 * span,
                              0.98 * span if sign > 0 else -0.98 * span)
    u = (s - new_crit) / (far - new_crit)          # 0 at the new critical point, 1 at the end
    old_s = crit + np.clip(u, 0.0, 1.0) * span     # where the old curve had that fraction
    order = np.argsort(s)
    out = np.where(u <= 0, 0.0, np.interp(old_s, s[order], k[order]))
    out[np.abs(out) < 1e-12] = 0.0
    return out if rising else out[::-1]


def _table_records(body: str) -> list[list[str]]:
    """Table keywords have one record per table (TABDIMS NTSFUN of them), no empty terminator."""
    out, current = [], []
    for tok in tokenize(body):
        if tok == "/":
            out.append(current)
            current = []
        else:
            current.append(tok)
    return [r for r in out if r]


def _multiply_block(mults: list[Multiply | FaultMultiplier | RegionTransmissibility]) -> str:
    """The GRID-end block: MULTIPLY (everywhere, then boxes), MULTIREG (regions), MULTFLT
    (faults), MULTREGT (between regions). The records without a box come first: a MULTIPLY
    record whose box is defaulted takes the box of the record before it (Eclipse's rule, which
    OPM follows), so a global factor written after a boxed one would act in that box only."""
    grid = "".join(m.record() + "\n" for m in sorted(
        (m for m in mults if isinstance(m, Multiply) and m.region is None),
        key=lambda m: m.box is not None))
    regions = "".join(m.region_records() for m in mults
                      if isinstance(m, Multiply) and m.region is not None)
    faults = "".join(m.records() for m in mults if isinstance(m, FaultMultiplier))
    between = "".join(m.record() for m in mults if isinstance(m, RegionTransmissibility))
    text = "-- parameter multipliers added by hmflow\n"
    for keyword, body in (("MULTIPLY", grid), ("MULTIREG", regions), ("MULTFLT", faults),
                          ("MULTREGT", between)):
        if body:
            text += f"{keyword}\n{body}/\n\n"
    return text


def _render_file(file: Path, info: DeckInfo, mults: list[Multiply], skins: list[SetSkin],
                 state: dict) -> str:
    """Text of ``file`` with edits applied; includes that need edits are inlined."""
    items: list[ItemMultiply] = state["items"]
    tables: list[TableTransform] = state["tables"]
    blocks = split_blocks(file.read_text(errors="replace"), info.keyword_names)
    out: list[str] = []
    for block in blocks:
        if block.keyword in SECTIONS:
            if state["section"] == "GRID" and mults and not state["multiplied"]:
                out.append(_multiply_block(mults))
                state["multiplied"] = True
            state["section"] = block.keyword
        if block.keyword == "INCLUDE":
            target = include_target(block)
            path = resolve_include(target or "", file, info.path.parent)
            if _needs_inlining(path, info, skins, state):
                out.append(f"-- inlined by hmflow from {path}\n")
                out.append(_render_file(path, info, mults, skins, state))
                out.append("\n")
            else:
                out.append(f"INCLUDE\n  '{path}' /\n\n")
        elif block.keyword == "COMPDAT" and (skins or state["pimults"] or state["moves"]):
            written = _rewrite_compdat(block, skins, file) if skins else block
            out.extend(written.lines)
            active = [m for m in state["pimults"] if m.start_day is None or m in state["dated"]]
            out.append(wpimult_block(block, active, state["pi_applied"]))
            state["completed"].update(r[0].strip("'\"") for r in records(block.body) if r)
            keep_connections(written, file, state)
        elif (block.keyword in ("DATES", "TSTEP") and state["section"] == "SCHEDULE"
              and (any(m.start_day is not None for m in state["pimults"]) or state["moves"])):
            out.append(dated_steps(block, info, state))
        elif any(e.keyword == block.keyword for e in items):
            out.extend(_rewrite_items(block, [e for e in items if e.keyword == block.keyword],
                                      file).lines)
            state["done"].add(block.keyword)
        elif any(e.keyword == block.keyword for e in tables):
            out.extend(_rewrite_tables(block, [e for e in tables if e.keyword == block.keyword],
                                       file).lines)
            state["done"].add(block.keyword)
        else:
            out.extend(block.lines)
    return "".join(out)


def _needs_inlining(path: Path, info: DeckInfo, skins: list[SetSkin], state: dict) -> bool:
    """Inline an include only if it holds something to edit (COMPDAT, or the GRID end)."""
    if path.suffix.upper() in {".GRDECL", ".GEO", ".PRP", ".INC"} and path.stat().st_size > 2**20:
        return False
    text = path.read_text(errors="replace")
    names = {b.keyword for b in split_blocks(text, info.keyword_names)}
    touched = {e.keyword for e in state["items"] + state["tables"]}
    if any(m.start_day is not None for m in state["pimults"]) or state["moves"]:
        touched |= {"DATES", "TSTEP"}
    return bool(((skins or state["pimults"] or state["moves"]) and "COMPDAT" in names)
                or (names & touched)
                or (state["section"] == "GRID" and names & set(SECTIONS)))


def render_deck(info: DeckInfo, edits: list[Edit]) -> str:
    """The per-run deck text for ``edits`` applied to the deck described by ``info``."""
    mults = [e for e in edits if isinstance(e, GRID_END)]
    skins = [e for e in edits if isinstance(e, SetSkin)]
    state = {"section": None, "multiplied": False, "done": set(),
             "items": [e for e in edits if isinstance(e, ItemMultiply)],
             "tables": [e for e in edits if isinstance(e, TableTransform)],
             "pimults": [e for e in edits if isinstance(e, PiMultiplier)], "pi_applied": set(),
             "step": 0, "dated": [], "completed": set(), "connections": [], "moved": [],
             "moves": [e for e in edits if isinstance(e, Recompletion)]}
    text = _render_file(info.path, info, mults, skins, state)
    late = [m for m in state["pimults"] if m.start_day is not None and m not in state["dated"]]
    late += [m for m in state["moves"] if m not in state["moved"]]
    if late:
        what = ("productivity multiplier" if isinstance(late[0], PiMultiplier) else
                "recompletion")
        wells = list(getattr(late[0], "wells", ())) or [getattr(late[0], "well", "")]
        raise CaseError([Problem(str(info.path), f"the {what} of {wells}"
                                 f" starts at day {late[0].start_day:g}, after the schedule's "
                                 f"last report step (day {info.end_days:g})",
                                 f"give a start_day up to {info.end_days:g}")])
    missing = {e.keyword for e in state["items"] + state["tables"]} - state["done"]
    unreached = sorted({w for e in state["pimults"] for w in e.wells} - state["pi_applied"])
    if unreached:
        raise CaseError([Problem(str(info.path), f"no COMPDAT connects {unreached}, so their "
                                 "productivity multiplier (WPIMULT) would change nothing",
                                 "name wells the deck completes, or move a COMPDAT that sits in "
                                 "a large include file into the deck")])
    if missing:
        raise CaseError([Problem(str(info.path), f"the deck has no {sorted(missing)} keyword to edit",
                                 "choose a keyword the deck defines")])
    if mults and not state["multiplied"]:
        raise CaseError([Problem(str(info.path), "no section keyword (EDIT or PROPS) follows GRID,"
                                 " so hmflow cannot place the MULTIPLY block",
                                 "make sure the deck has a GRID and a PROPS section")])
    header = "-- per-run deck written by hmflow; the base deck is " + str(info.path) + "\n"
    return header + text


def prepare_run_deck(base_deck: Path, values: dict[str, float], space: ParameterSpace,
                     run_dir: Path, info: DeckInfo | None = None) -> Path:
    """Write ``run_dir/<NAME>.DATA`` for ``values`` and return its path.

    ``run_dir`` is created; an existing deck there is never overwritten (FileExistsError).
    """
    info = info or DeckInfo.inspect(Path(base_deck))
    run_dir.mkdir(parents=True, exist_ok=True)
    target = run_dir / info.path.name.upper()
    text = render_deck(info, edits_for(space, values, info))
    with open(target, "x") as fh:
        fh.write(text)
    return target
