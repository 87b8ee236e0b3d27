"""What hmflow needs to know about a base deck, read with OPM's own parser (opm.io).

Parsing is fast (about 0.1 s for PUNQ-S3) and spends no simulator time, so ``hmflow check``
uses it to report a deck OPM cannot read, missing include files, unknown wells and
observation days outside the schedule before anything runs.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from hmcore.eclipse.cells import MILLIDARCY_M2, REGION_KEYWORDS, CellProperties
from hmcore.eclipse.history import History, read_history
from hmcore.eclipse.includes import resolve_include
from hmcore.eclipse.lexer import include_target, split_blocks
from hmcore.errors import CaseError, Problem

UNIT_SYSTEMS = ("METRIC", "FIELD", "LAB", "PVT-M")
SECTION_NAMES = ("RUNSPEC", "GRID", "EDIT", "PROPS", "REGIONS", "SOLUTION", "SUMMARY", "SCHEDULE")


@dataclass(frozen=True)
class WellInfo:
    name: str
    producer: bool
    connections: tuple[tuple[int, int, int], ...]  # 1-based (i, j, k)


@dataclass(frozen=True)
class DeckInfo:
    """Facts about a deck: wells, grid, schedule (days from START) and property ranges."""

    path: Path
    keyword_names: frozenset[str]
    wells: dict[str, WellInfo]
    dims: tuple[int, int, int]
    nactive: int
    start: datetime
    report_days: tuple[float, ...]
    properties: dict[str, tuple[float, float]] = field(default_factory=dict)  # (min, max); PERM* in mD
    cells: CellProperties | None = field(default=None, repr=False, compare=False)
    history: History = field(default_factory=History, repr=False, compare=False)  # WCONHIST...
    faults: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()  # what OPM Flow tolerates (file and line in the text)
    regions: dict[str, tuple[int, ...]] = field(default_factory=dict)  # MULTNUM... -> numbers
    grid_keywords: frozenset[str] = frozenset()  # keywords of the GRID section

    @property
    def unit_system(self) -> str:
        """METRIC (the Eclipse default), FIELD, LAB or PVT-M, from the RUNSPEC keyword."""
        return next((u for u in UNIT_SYSTEMS if u in self.keyword_names), "METRIC")

    @property
    def producers(self) -> list[str]:
        return [w.name for w in self.wells.values() if w.producer]

    @property
    def end_days(self) -> float:
        return self.report_days[-1]

    @staticmethod
    def inspect(path: Path) -> "DeckInfo":
        """Parse ``path`` with opm.io; raise CaseError listing every problem found."""
        return DeckInfo.inspect_parsed(path)[0]

    @staticmethod
    def inspect_parsed(path: Path) -> tuple["DeckInfo", "ParsedDeck"]:
        """As :meth:`inspect`, with OPM's parsed deck and state too, for a caller that reads
        more of them (a field's grid, :func:`hmcore.fields.grid.from_parsed`) without parsing
        the deck a second time."""
        path = Path(path).resolve()
        if not path.is_file():
            raise CaseError([Problem(str(path), "deck file not found",
                                     "check the 'deck' key of the case file")])
        problems = missing_includes(path)
        if problems:
            raise CaseError(problems)
        deck, state, schedule, warnings = _parse(path)
        names = frozenset(kw.name for kw in deck) | frozenset(SECTION_NAMES) | {"INCLUDE"}
        wells = {}
        for name in schedule.well_names("*"):
            producer = False
            conns: set[tuple[int, int, int]] = set()
            for step in range(len(schedule.reportsteps)):
                try:
                    well = schedule.get_well(name, step)
                except Exception:  # well not yet defined at this step
                    continue
                producer = producer or bool(well.isproducer())
                conns.update((c.i + 1, c.j + 1, c.k + 1) for c in well.connections())
            wells[name] = WellInfo(name, producer, tuple(sorted(conns)))
        start = schedule.start
        days = tuple(round((t - start).total_seconds() / 86400.0, 4) for t in schedule.reportsteps)
        grid = state.grid()
        props = {}
        fp = state.field_props()
        for kw in ("PORO", "PERMX", "PERMY", "PERMZ", "NTG"):
            if kw in fp:
                arr = np.asarray(fp.get_double_array(kw))
                if arr.size:
                    scale = 1.0 / MILLIDARCY_M2 if kw.startswith("PERM") else 1.0
                    props[kw] = (float(arr.min()) * scale, float(arr.max()) * scale)
        info = DeckInfo(path, names, wells, (grid.nx, grid.ny, grid.nz), grid.nactive, start,
                        days, props, CellProperties.from_parsed(deck, state),
                        read_history(deck, days, wells), tuple(state.faultNames()), warnings,
                        _region_numbers(state), _grid_keywords(deck))
        return info, ParsedDeck(path, deck, state)


@dataclass(frozen=True, eq=False)
class ParsedDeck:
    """A deck as OPM's parser read it: opm.io's ``Deck`` and its ``EclipseState``. Kept only
    while a case is validated (opm.io's objects are not pickled with a case)."""

    path: Path
    deck: object = field(repr=False)
    state: object = field(repr=False)


def _region_numbers(state) -> dict[str, tuple[int, ...]]:
    fp = state.field_props()
    return {kw: tuple(int(v) for v in np.unique(np.asarray(fp.get_int_array(kw))))
            for kw in REGION_KEYWORDS if kw in fp}


def _grid_keywords(deck) -> frozenset[str]:
    section, names = None, set()
    for kw in deck:
        if kw.name in SECTION_NAMES:
            section = kw.name
        elif section == "GRID":
            names.add(kw.name)
    return frozenset(names)


def missing_includes(path: Path, main_dir: Path | None = None) -> list[Problem]:
    """Every INCLUDE (recursively) that names no file, a file that does not exist, or a file
    already being included (a cycle: OPM's parser would never end). Files are found by
    :func:`hmcore.eclipse.includes.resolve_include`, the one INCLUDE resolver."""
    path = Path(path).resolve()
    main_dir = Path(main_dir or path.parent).resolve()
    problems: list[Problem] = []
    done: set[Path] = set()

    def visit(file: Path, chain: tuple[Path, ...]) -> None:
        done.add(file)
        line_no = 1
        for block in split_blocks(file.read_text(errors="replace"), {"INCLUDE"}):
            if block.keyword == "INCLUDE":
                where = f"{file} line {line_no}"
                target = include_target(block)
                found = resolve_include(target, file, main_dir) if target else None
                if not target:
                    problems.append(Problem(where, "INCLUDE names no file",
                                            "write INCLUDE, then 'file.inc' / on the next line"))
                elif not found.is_file():
                    looked = [str(found.parent)] if Path(target).is_absolute() else sorted(
                        {str(main_dir), str(file.parent)})
                    problems.append(Problem(where, f"INCLUDE file '{target}' not found "
                                            f"(looked in {looked})",
                                            "fix the path or copy the file next to the deck"))
                elif found.resolve() in chain:
                    cycle = " -> ".join(p.name for p in (*chain[chain.index(found.resolve()):],
                                                         found.resolve()))
                    problems.append(Problem(where, f"INCLUDE '{target}' makes a cycle ({cycle}): "
                                            "the deck would include itself without end",
                                            "remove the INCLUDE that leads back"))
                elif found.resolve() not in done:
                    visit(found.resolve(), (*chain, found.resolve()))
            line_no += len(block.lines)

    visit(path, (path,))
    return problems


# parse errors OPM Flow reports as warnings and runs on (its default parsing strictness):
# e.g. a stray '/' line after TUNING in Norne's schedule
FLOW_TOLERATES = ("PARSE_RANDOM_SLASH", "PARSE_MISSING_DIMS_KEYWORD", "SUMMARY_UNKNOWN_WELL",
                  "SUMMARY_UNKNOWN_GROUP")

_STDOUT_LOCK = threading.Lock()


@contextlib.contextmanager
def quiet_stdout():
    """Silence OPM's parser chatter on file descriptor 1 (it prints 'Reading ...').

    File descriptor 1 is process-wide: the lock keeps two threads from interleaving the
    redirect and its undo (which would leave stdout pointing at a deleted file).
    """
    with _STDOUT_LOCK:
        with _redirect_fd1():
            yield


@contextlib.contextmanager
def _redirect_fd1():
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        try:
            yield
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)


def _parse(path: Path):
    import opm.io
    from opm.io.ecl_state import EclipseState
    from opm.io.parser import ParseContext, Parser
    from opm.io.schedule import Schedule

    warnings: list[str] = []
    try:
        with quiet_stdout():
            try:
                deck = Parser().parse(str(path), ParseContext())
            except Exception as strict:  # what OPM Flow itself tolerates is only a warning
                tolerated = [(name, opm.io.action.warn) for name in FLOW_TOLERATES]
                deck = Parser().parse(str(path), ParseContext(tolerated))
                warnings.append(" ".join(str(strict).split()))
            state = EclipseState(deck)
            schedule = Schedule(deck, state)
    except Exception as exc:  # opm.io raises RuntimeError/ValueError with the parser's text
        raise CaseError([Problem(str(path), f"OPM cannot parse the deck: {exc}",
                                 "fix the keyword named above; run OPM Flow on the deck by "
                                 "hand to see its full message")]) from exc
    return deck, state, schedule, tuple(warnings)
