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

from hmcore.deck_cells import MILLIDARCY_M2, CellProperties
from hmcore.eclipse_lexer import include_target, split_blocks
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
        path = Path(path).resolve()
        if not path.is_file():
            raise CaseError([Problem(str(path), "deck file not found",
                                     "check the 'deck' key of the case file")])
        problems = missing_includes(path)
        if problems:
            raise CaseError(problems)
        deck, state, schedule = _parse(path)
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
        return DeckInfo(path, names, wells, (grid.nx, grid.ny, grid.nz), grid.nactive, start,
                        days, props, CellProperties.from_parsed(deck, state))


def missing_includes(path: Path, main_dir: Path | None = None, seen: set | None = None
                     ) -> list[Problem]:
    """Every INCLUDE (recursively) that names a file that does not exist."""
    main_dir = main_dir or path.parent
    seen = seen if seen is not None else set()
    problems = []
    text = path.read_text(errors="replace")
    line_no = 1
    for block in split_blocks(text, {"INCLUDE"}):
        if block.keyword == "INCLUDE":
            target = include_target(block)
            if not target:
                problems.append(Problem(f"{path} line {line_no}", "INCLUDE names no file",
                                        "write INCLUDE, then 'file.inc' / on the next line"))
            else:
                cands = [Path(target)] if Path(target).is_absolute() else [
                    main_dir / target, path.parent / target]
                found = next((c for c in cands if c.is_file()), None)
                if found is None:
                    problems.append(Problem(
                        f"{path} line {line_no}", f"INCLUDE file '{target}' not found "
                        f"(looked in {sorted({str(c.parent) for c in cands})})",
                        "fix the path or copy the file next to the deck"))
                elif found.resolve() not in seen:
                    seen.add(found.resolve())
                    problems.extend(missing_includes(found, main_dir, seen))
        line_no += len(block.lines)
    return problems


_STDOUT_LOCK = threading.Lock()


@contextlib.contextmanager
def _quiet_stdout():
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
    from opm.io.ecl_state import EclipseState
    from opm.io.parser import ParseContext, Parser
    from opm.io.schedule import Schedule

    try:
        with _quiet_stdout():
            deck = Parser().parse(str(path), ParseContext())
            state = EclipseState(deck)
            schedule = Schedule(deck, state)
    except Exception as exc:  # opm.io raises RuntimeError/ValueError with the parser's text
        raise CaseError([Problem(str(path), f"OPM cannot parse the deck: {exc}",
                                 "fix the keyword named above; run OPM Flow on the deck by "
                                 "hand to see its full message")]) from exc
    return deck, state, schedule
