"""Checks that need the parsed deck and run before any simulator or Prefect start (called by
:func:`hmcore.cases.load_case`, the single entry of ``check``, ``run``, ``evaluate``,
``diagnose`` and ``bench``): each parameter acts on the deck, the simulator command resolves.

Every problem is a :class:`~hmcore.errors.Problem` naming the file and the key or parameter,
the rule broken and a fix; callers collect them and raise them together.
"""

from __future__ import annotations

import difflib
import shlex
import shutil
import string
from pathlib import Path

from hmcore.eclipse.deck_info import DeckInfo
from hmcore.eclipse.includes import deck_files
from hmcore.eclipse.lexer import expand_repeats, records, split_blocks
from hmcore.errors import CaseError, Problem
from hmcore.model.parameters import (
    RELPERM_COLUMNS,
    TABLE_MULTIPLIABLE,
    Parameter,
    ParameterKind,
    ParameterSpace,
)
from hmcore.model.run_deck import edits_for, render_deck

OPM_BACKENDS = ("", "opm", "opm-flow")
PLACEHOLDERS = ("deck", "run_dir", "case", "threads", "processes")


def did_you_mean(word: str, choices, cutoff: float = 0.6) -> str:
    """`` (did you mean 'x'?)`` for the nearest of ``choices``, else ''."""
    near = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=cutoff)
    return f" (did you mean {near[0]!r}?)" if near else ""


# ----------------------------------------------------------------------------- simulator
def simulator_problems(backend: str, key: str) -> list[Problem]:
    """``[simulator] backend`` (or ``--simulator``; ``key`` says where it was given): 'opm',
    or a command template that parses (shell words), names only known placeholders and whose
    program exists."""
    if backend in OPM_BACKENDS:  # as hmcore.simulation.simulator.make_simulator reads it
        return []
    fix_known = f"use 'opm' or a command with the placeholders {{{'}, {'.join(PLACEHOLDERS)}}}"
    try:
        words = shlex.split(backend)
    except ValueError as exc:
        return [Problem(key, f"the command {backend!r} cannot be split into words ({exc})",
                        "close the quote or escape it")]
    if not words:
        return [Problem(key, "the command is empty", fix_known)]
    problems = []
    used: set[str] = set()
    for word in words:
        try:
            fields = [f for _, f, _, _ in string.Formatter().parse(word) if f is not None]
        except ValueError as exc:
            problems.append(Problem(key, f"the word {word!r} is not a valid template ({exc})",
                                    "write literal braces as {{ and }}"))
            continue
        for name in fields:
            if name not in PLACEHOLDERS:
                problems.append(Problem(key, f"unknown placeholder {{{name}}} in {backend!r}"
                                        + did_you_mean(name, PLACEHOLDERS), fix_known))
            used.add(name)
    if "deck" not in used and not problems:
        problems.append(Problem(key, f"the command {backend!r} does not name the deck",
                                "pass the deck to the simulator with {deck}"))
    program = words[0]
    if "{" in program:
        problems.append(Problem(key, f"the program {program!r} is a placeholder",
                                "start the command with the simulator's program"))
    elif "/" in program and not Path(program).is_absolute():
        problems.append(Problem(key, f"the program {program!r} is a relative path; the "
                                "simulator runs in each call's own run folder",
                                "give the program's absolute path, or a name on PATH"))
    elif shutil.which(program) is None:
        problems.append(Problem(key, f"the program {program!r} is not found"
                                + ("" if "/" in program else " on PATH") + " or not executable",
                                "install it, fix the name, or give its absolute path"))
    return problems


# ----------------------------------------------------------------------------- parameters
def deck_reference_problems(params, info: DeckInfo, where: str) -> list[Problem]:
    """What each parameter names exists in the deck: its wells, region keyword and numbers,
    faults, layers, box and GRID keywords. A ``latent`` parameter is hmflow's own and names
    nothing; one given in a case file (``where``) is refused, and so is a ``trend`` or a
    ``recomplete`` (a hidden truth's edit, not a calibration parameter)."""
    problems = []
    nx, ny, nz = info.dims
    for p in params:
        if p.kind == ParameterKind.LATENT:
            if where.endswith("[[parameters]]"):
                problems.append(Problem(f"{where} '{p.name}'", "kind 'latent' is hmflow's own: "
                                        "the coefficient of a mode of the fields' prior",
                                        "give the case a [latent] section, which makes them"))
            continue
        if p.kind in (ParameterKind.TREND, ParameterKind.RECOMPLETE) and \
                where.endswith("[[parameters]]"):
            problems.append(Problem(f"{where} '{p.name}'", f"kind '{p.kind.value}' is hmflow's "
                                    "own: the edit of a hidden truth (hmcore.scenarios.generators)",
                                    "use kind 'multiply' (in a box) or 'wpimult' (with a "
                                    "start_day)"))
            continue
        unknown = [w for w in p.wells if w not in info.wells]
        if unknown:
            problems.append(Problem(f"{where} '{p.name}'", f"unknown well(s) {unknown}"
                                    + (did_you_mean(unknown[0], info.wells) if len(unknown) == 1 else ""),
                                    f"the deck's wells are {sorted(info.wells)}"))
        problems.extend(_region_problems(p, info, where))
        missing_faults = [f for f in p.faults if f not in info.faults]
        if missing_faults:
            problems.append(Problem(f"{where} '{p.name}'", f"unknown fault(s) {missing_faults}"
                                    + (did_you_mean(missing_faults[0], info.faults)
                                       if len(missing_faults) == 1 else ""),
                                    f"the deck's faults (FAULTS keyword) are "
                                    f"{sorted(info.faults) or 'none'}"))
        bad_layers = [k for k in p.layers if not 1 <= k <= nz]
        if bad_layers:
            problems.append(Problem(f"{where} '{p.name}'", f"layer(s) {bad_layers} outside 1..{nz}",
                                    "layers are 1-based k indices"))
        if p.box is not None:
            i1, i2, j1, j2, k1, k2 = p.box
            if i2 > nx or j2 > ny or k2 > nz:
                problems.append(Problem(f"{where} '{p.name}'", f"box {p.box} outside the grid "
                                        f"{nx}x{ny}x{nz}", "use 1-based indices inside the grid"))
        for kw in p.keywords:
            if kw.upper() in ("PORO", "PERMX", "PERMY", "PERMZ", "NTG") and \
                    kw.upper() not in info.properties:
                problems.append(Problem(f"{where} '{p.name}'", f"the deck defines no {kw}",
                                        "multiply a keyword the GRID section defines"))
    return problems


def _region_problems(p, info: DeckInfo, where: str) -> list[Problem]:
    """A region parameter names a region keyword the GRID section defines, and its numbers."""
    if p.region is None and p.kind != "multregt":
        return []
    keyword = (p.region or "MULTNUM").upper()
    if keyword not in info.regions or keyword not in info.grid_keywords:
        defined = sorted(k for k in info.regions if k in info.grid_keywords)
        return [Problem(f"{where} '{p.name}'", f"the deck's GRID section defines no {keyword}, "
                        "which MULTIREG/MULTREGT read", f"use one it defines ({defined or 'none'})"
                        f" or add {keyword} to the GRID section")]
    unknown = [n for n in p.region_numbers if n not in info.regions[keyword]]
    if unknown:
        return [Problem(f"{where} '{p.name}'", f"{keyword} has no region(s) {unknown}",
                        f"the deck's {keyword} values are {list(info.regions[keyword])}")]
    return []


UNCONDITIONAL = (ParameterKind.MULTIPLY, ParameterKind.MULTREGT, ParameterKind.FAULT)
"""Kinds whose edit is always written with the value (a MULTIPLY, MULTREGT or MULTFLT record
at the end of GRID): once the deck renders, their text changes with the value by itself."""


def parameter_problems(space_params, info: DeckInfo, where: str) -> list[Problem]:
    """Each parameter acts on the deck: what it names exists (records, items), and applying it
    dry changes the deck text. The per-run deck is rendered once with every parameter at its
    low bound (it must render), and each parameter whose edit depends on the deck (skin,
    wpimult, item_multiply, relperm, table_multiply) is applied alone at its low and at its high bound: the
    two texts must differ. (Alone: a parameter that another one overrides, a global skin
    under per-well skins, is not refused.)"""
    problems: list[Problem] = []
    blocks = None
    checked = []
    for p in space_params:
        own: list[Problem] = []
        if p.kind in (ParameterKind.ITEM_MULTIPLY, ParameterKind.RELPERM,
                      ParameterKind.TABLE_MULTIPLY):
            if blocks is None:
                blocks = _keyword_blocks(info)
            own = (_item_problems(p, blocks, info, where) if p.kind == ParameterKind.ITEM_MULTIPLY
                   else _table_problems(p, blocks, info, where))
        problems.extend(own)
        if not own and p.name not in {c.name for c in checked}:  # (duplicates: reported)
            checked.append(p)
    if not checked:
        return problems
    lows = {p.name: p.low for p in checked}
    _, failed = _render(checked, lows, info, where)
    if failed:  # name the parameter(s) that cannot be applied
        return problems + [x for p in checked
                           for x in _render([p], {p.name: p.low}, info, where, p)[1]]
    for p in checked:
        if p.kind in UNCONDITIONAL:
            continue
        low, failed = _render([p], {p.name: p.low}, info, where, p)
        high, failed_high = _render([p], {p.name: p.high}, info, where, p)
        problems.extend(failed or failed_high)
        if not (failed or failed_high) and high == low:
            problems.append(Problem(f"{where} '{p.name}'", f"the deck text is the same at "
                                    f"low={p.low:g} and high={p.high:g}: this {p.kind.value} "
                                    "parameter changes nothing in the deck",
                                    "check the wells, layers, records or keyword it names"))
    return problems


def _render(params, values: dict[str, float], info: DeckInfo, where: str,
            named: Parameter | None = None) -> tuple[str, list[Problem]]:
    """The per-run deck text for ``values`` and the problems of rendering it (named after
    ``named``, else after every parameter rendered)."""

    space = ParameterSpace(parameters=tuple(params))
    at = f"{where} '{named.name}'" if named else f"{where} {[p.name for p in params]}"
    try:
        return render_deck(info, edits_for(space, values, info)), []
    except CaseError as exc:
        return "", [Problem(at, f"applying it to the deck fails: {x.what}", x.fix)
                    for x in exc.problems]
    except (ValueError, IndexError, KeyError) as exc:
        return "", [Problem(at, f"applying it to the deck fails: {exc}",
                            "check the keyword, item and match it names")]


def _keyword_blocks(info: DeckInfo) -> list[tuple[Path, object]]:
    out = []
    for file in deck_files(info.path):
        if file.stat().st_size > 2**26:  # a huge grid include holds no keyword to edit here
            continue
        out.extend((file, b) for b in split_blocks(file.read_text(errors="replace"),
                                                  info.keyword_names))
    return out


def _item_problems(p: Parameter, blocks, info: DeckInfo, where: str) -> list[Problem]:
    keyword = p.keywords[0].upper()
    at = f"{where} '{p.name}'"
    found = [(f, b) for f, b in blocks if b.keyword == keyword]
    if not found:
        return [Problem(at, f"the deck has no {keyword} keyword, so item_multiply acts on "
                        "nothing" + did_you_mean(keyword, info.keyword_names),
                        "name a keyword the deck defines")]
    recs = [(f, r) for f, b in found for r in (expand_repeats(x) for x in records(b.body)) if r]
    if p.match is not None:
        firsts = sorted({r[0].strip("'\"") for _, r in recs})
        recs = [(f, r) for f, r in recs if r[0].strip("'\"") == p.match]
        if not recs:
            return [Problem(at, f"match = {p.match!r} selects no {keyword} record (their first "
                            f"items are {firsts}), so the parameter would change nothing",
                            f"use one of {firsts}, or remove match")]
    problems = []
    for file, rec in recs:
        if len(rec) < p.item:
            problems.append(Problem(at, f"{keyword} record '{' '.join(rec)}' in {file} has "
                                    f"{len(rec)} item(s), no item {p.item}",
                                    f"item counts from 1 and must be <= {len(rec)}"))
        elif rec[p.item - 1] == "1*":
            problems.append(Problem(at, f"{keyword} item {p.item} is defaulted (1*) in record "
                                    f"'{' '.join(rec)}' in {file}; a default cannot be "
                                    "multiplied", f"write the value of item {p.item} explicitly"))
        else:
            try:
                float(rec[p.item - 1].replace("D", "E").replace("d", "e"))
            except ValueError:
                problems.append(Problem(at, f"{keyword} item {p.item} is "
                                        f"{rec[p.item - 1]!r} in record '{' '.join(rec)}' in "
                                        f"{file}, not a number", "choose a numeric item"))
        if problems:
            break  # one record tells the rule
    return problems


def _table_problems(p: Parameter, blocks, info: DeckInfo, where: str) -> list[Problem]:
    keyword = p.keywords[0].upper()
    if not any(b.keyword == keyword for _, b in blocks):
        kinds = RELPERM_COLUMNS if p.kind == ParameterKind.RELPERM else TABLE_MULTIPLIABLE
        tables = sorted({b.keyword for _, b in blocks} & set(kinds))
        return [Problem(f"{where} '{p.name}'", f"the deck has no {keyword} table, so the "
                        f"{p.kind.value} parameter acts on nothing", f"use a table the deck defines "
                        f"({tables or 'none'})")]
    return []
