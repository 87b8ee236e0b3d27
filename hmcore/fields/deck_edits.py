"""The deck's own GRID edits that a member's include comes after.

A member's fields are written as an INCLUDE at the end of the deck's GRID section
(:mod:`hmcore.fields.members`), after every GRID edit of the deck. An edit that derives one
property from another has then already been done with the deck's values: PUNQ-S3's
``COPY 'PERMX' 'PERMY'`` makes PERMY the deck's PERMX (the truth's, there), and a member
whose PERMX varies would keep that PERMY for every member, silently: the members would share
the truth's horizontal permeability in one direction. :func:`copy_problems` names every such
edit before anything runs, with the ways out (the field's ``copies``, a field of its own for
the target, or an edit of the deck). The other way round, an arithmetic edit of a keyword a
field writes (``MULTIPLY PERMZ 0.1``) is replaced by the member's values: the deck's factor
would be lost without a word, and :func:`scaling_problems` names it.

The edits are read from the deck OPM's parser has already read (``opm.io`` ``Deck``, whose
keywords carry no file line): ``COPY`` (source, target, box), ``COPYREG`` (source, target,
region), ``MULTIPLY``/``ADD`` (keyword, value, box) and ``MULTIREG``/``ADDREG`` (keyword,
value, region); a box or a region does not matter, since any cell is enough. ``EQUALS`` is
how a deck defines a property in the first place; a member's values replacing it are the
point.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from hmcore.eclipse.deck_info import SECTION_NAMES
from hmcore.errors import Problem
from hmcore.fields.spec import FieldSpec

COPY_KEYWORDS = ("COPY", "COPYREG")
"""GRID edits that set one keyword from another's values."""
SCALING_KEYWORDS = ("MULTIPLY", "ADD", "MULTIREG", "ADDREG")
"""GRID edits that change a keyword's values in place."""


@dataclass(frozen=True)
class GridCopy:
    """One record of a ``COPY`` or ``COPYREG`` in the deck's GRID section."""

    keyword: str
    source: str
    target: str


@dataclass(frozen=True)
class GridScaling:
    """One record of a ``MULTIPLY``, ``ADD``, ``MULTIREG`` or ``ADDREG`` in the GRID section."""

    keyword: str
    target: str
    value: float


def _grid_records(deck: Iterable, names: tuple[str, ...]):
    """(keyword name, record) of every record of ``names`` in an opm.io ``Deck``'s GRID
    section, in deck order."""
    section = None
    for kw in deck:
        if kw.name in SECTION_NAMES:
            section = kw.name
        elif section == "GRID" and kw.name in names:
            yield from ((kw.name, rec) for rec in kw)


def grid_copies(deck: Iterable) -> list[GridCopy]:
    """Every ``COPY``/``COPYREG`` record of an opm.io ``Deck``'s GRID section, in deck order
    (keyword names upper case)."""
    return [GridCopy(name, rec[0].get_str(0).upper(), rec[1].get_str(0).upper())
            for name, rec in _grid_records(deck, COPY_KEYWORDS)]


def grid_scalings(deck: Iterable) -> list[GridScaling]:
    """Every ``MULTIPLY``/``ADD``/``MULTIREG``/``ADDREG`` record of the GRID section."""
    return [GridScaling(name, rec[0].get_str(0).upper(), float(rec[1].get_raw(0)))
            for name, rec in _grid_records(deck, SCALING_KEYWORDS)]


def scaling_problems(fields: Sequence[FieldSpec], scalings: Sequence[GridScaling],
                     deck_name: str) -> list[Problem]:
    """A problem for each GRID ``MULTIPLY``/``ADD`` (and their region forms) of a keyword a
    field writes: the members' include replaces the edited values, so the factor is lost.
    A multiplication by 1 or an addition of 0 changes nothing and is no problem."""
    writer = {kw: f for f in fields for kw in f.written}
    problems = []
    for e in scalings:
        field = writer.get(e.target)
        neutral = 1.0 if e.keyword.startswith("MULT") else 0.0
        if field is None or e.value == neutral:
            continue
        problems.append(Problem(
            f"field '{field.name}'",
            f"the deck {deck_name} edits {e.target} in its GRID section ({e.keyword} "
            f"'{e.target}' {e.value:g}), which the members' include replaces: every member "
            f"would lose that edit",
            f"state the prior and bounds of field '{field.name}' for the edited values and "
            f"remove the {e.keyword} of {e.target} from the deck"))
    return problems


def copy_problems(fields: Sequence[FieldSpec], copies: Sequence[GridCopy],
                  deck_name: str) -> list[Problem]:
    """A problem for each GRID copy from a keyword a field writes (its keyword or one of its
    ``copies``, or a keyword copied from one in turn) to a keyword no field writes: the members
    would keep the deck's values there. ``where`` is ``field '<name>'`` (the caller adds the
    case file), one problem per field and target, all at once."""
    writer = {kw: f for f in fields for kw in f.written}
    derived: dict[str, FieldSpec] = {}  # a target copied from a field's keyword, in turn
    problems, seen = [], set()
    for c in copies:
        field = writer.get(c.source) or derived.get(c.source)
        if field is None or c.target in writer:
            continue
        derived[c.target] = field
        if (field.name, c.target) in seen:
            continue
        seen.add((field.name, c.target))
        problems.append(Problem(
            f"field '{field.name}'",
            f"the deck {deck_name} sets {c.target} from {c.source} in its GRID section "
            f"({c.keyword} '{c.source}' '{c.target}'), before the members' include: {c.target} "
            f"would keep the deck's own values in every member while {c.source} varies",
            f"add copies = [\"{c.target}\"] to field '{field.name}' (the same values), give "
            f"{c.target} a field of its own, or set {c.target} without {c.keyword} in the deck"))
    return problems
