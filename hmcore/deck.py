"""Deck preparation: write a per-run deck with parameter edits into an isolated run directory.

The base deck is never modified. The per-run deck is a copy of the main file (and of any include
file that must change) with

* a ``MULTIPLY`` block inserted at the end of the GRID section, i.e. just before the next
  section keyword (``EDIT`` or ``PROPS``), so it acts after every grid property and after
  ``COPY PERMX PERMY``;
* COMPDAT item 11 (skin) rewritten for the targeted wells (and layers);
* every ``INCLUDE`` path made absolute (unchanged include files are not copied).

Keywords are located by a small Eclipse lexer (comments, quotes, ``N*`` repeats, ``/``
terminators) restricted to the keywords OPM's parser found in the deck, never by line numbers.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass
from pathlib import Path

from hmcore.deck_info import SECTION_NAMES as SECTIONS
from hmcore.deck_info import DeckInfo
from hmcore.includes import resolve_include
from hmcore.eclipse_lexer import (Block, expand_repeats, include_target, records, split_blocks,
                                  tokenize)
from hmcore.errors import CaseError, Problem
from hmcore.parameters import Parameter, ParameterSpace

_COMPDAT_SKIN_ITEM = 11


# ----------------------------------------------------------------------------- edits
@dataclass(frozen=True)
class Multiply:
    """Multiply grid keyword ``keyword`` by ``factor`` (in a 1-based box when given)."""

    keyword: str
    factor: float
    box: tuple[int, int, int, int, int, int] | None = None

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
class TableTransform:
    """Scale (``mode="scale"``) or reshape (``mode="power"``) column ``column`` of tables."""

    keyword: str
    column: int
    mode: str
    value: float


Edit = Multiply | SetSkin | ItemMultiply | TableTransform
TABLE_COLUMNS = {"SWOF": 4, "SGOF": 4, "SLGOF": 4, "SWFN": 3, "SGFN": 3, "SOF3": 3, "SOF2": 2}


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
        return [Multiply(k.upper(), value, p.box) for k in p.keywords]
    if p.kind == "item_multiply":
        return [ItemMultiply(p.keywords[0].upper(), int(p.item), value, p.match)]
    if p.kind == "relperm":
        return [TableTransform(p.keywords[0].upper(), int(p.item or 2), p.mode, value)]
    wells = p.wells or tuple(info.producers)
    return [SetSkin(tuple(wells), value, p.layers)]


# ----------------------------------------------------------------------------- rendering
def _format_compdat_record(tokens: list[str]) -> str:
    return " " + " ".join(tokens) + " /\n"


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
            new_lines.append(_format_compdat_record(p))
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
    new_lines = [block.lines[0], f"-- records rewritten by hmflow (item multipliers)\n"]
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
        new_lines.append(_format_compdat_record(items))
    new_lines.append("/\n\n")
    return Block(block.keyword, new_lines)


def _rewrite_tables(block: Block, edits: list[TableTransform], file: Path) -> Block:
    """Saturation tables of ``block.keyword`` with one column scaled or reshaped."""
    import numpy as np

    ncol = TABLE_COLUMNS[block.keyword]
    new_lines = [block.lines[0], "-- tables rewritten by hmflow (relative permeability)\n"]
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
            if e.mode == "scale":
                col = np.minimum(col * e.value, 1.0)
            elif top > 0:
                col = top * (col / top) ** e.value
            table[:, e.column - 1] = col
        new_lines += [" " + " ".join(f"{v:.8g}" for v in row) + "\n" for row in table]
        new_lines.append("/\n")
    new_lines.append("\n")
    return Block(block.keyword, new_lines)


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


def _multiply_block(mults: list[Multiply]) -> str:
    body = "".join(m.record() + "\n" for m in mults)
    return f"-- parameter multipliers added by hmflow\nMULTIPLY\n{body}/\n\n"


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
        elif block.keyword == "COMPDAT" and skins:
            out.extend(_rewrite_compdat(block, skins, file).lines)
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
    return bool((skins and "COMPDAT" in names) or (names & touched)
                or (state["section"] == "GRID" and names & set(SECTIONS)))


def render_deck(info: DeckInfo, edits: list[Edit]) -> str:
    """The per-run deck text for ``edits`` applied to the deck described by ``info``."""
    mults = [e for e in edits if isinstance(e, Multiply)]
    skins = [e for e in edits if isinstance(e, SetSkin)]
    state = {"section": None, "multiplied": False, "done": set(),
             "items": [e for e in edits if isinstance(e, ItemMultiply)],
             "tables": [e for e in edits if isinstance(e, TableTransform)]}
    text = _render_file(info.path, info, mults, skins, state)
    missing = {e.keyword for e in state["items"] + state["tables"]} - state["done"]
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
