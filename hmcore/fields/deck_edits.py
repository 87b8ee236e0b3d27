"""The deck's own GRID edits that a member's include comes after.

A member's fields are written as an INCLUDE at the end of the deck's GRID section
(:mod:`hmcore.fields.members`), after every GRID edit of the deck. An edit that derives one
property from another has then already been done with the deck's values: PUNQ-S3's
``COPY 'PERMX' 'PERMY'`` makes PERMY the deck's PERMX (the truth's, there), and a member
whose PERMX varies would keep that PERMY for every member, silently: the members would share
the truth's horizontal permeability in one direction. :func:`copy_problems` names every such
edit before anything runs, with the ways out (the field's ``copies``, a field of its own for
the target, or an edit of the deck).

The edits are read from the deck OPM's parser has already read (``opm.io`` ``Deck``, whose
keywords carry no file line): ``COPY`` (source, target, box) and ``COPYREG`` (source, target,
region); a box or a region does not matter, since any cell of the target keeps the deck's
value.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from hmcore.eclipse.deck_info import SECTION_NAMES
from hmcore.errors import Problem
from hmcore.fields.spec import FieldSpec

COPY_KEYWORDS = ("COPY", "COPYREG")
"""GRID edits that set one keyword from another's values."""


@dataclass(frozen=True)
class GridCopy:
    """One record of a ``COPY`` or ``COPYREG`` in the deck's GRID section."""

    keyword: str
    source: str
    target: str


def grid_copies(deck: Iterable) -> list[GridCopy]:
    """Every ``COPY``/``COPYREG`` record of an opm.io ``Deck``'s GRID section, in deck order
    (keyword names upper case, as OPM gives them)."""
    copies, section = [], None
    for kw in deck:
        if kw.name in SECTION_NAMES:
            section = kw.name
        elif section == "GRID" and kw.name in COPY_KEYWORDS:
            copies += [GridCopy(kw.name, rec[0].get_str(0).upper(), rec[1].get_str(0).upper())
                       for rec in kw]
    return copies


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
