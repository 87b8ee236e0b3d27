"""The field parameters and the ``[ensemble]`` section of a case file (issue 41).

A ``[[parameters]]`` entry with ``kind = "field"`` is a :class:`~hmcore.fields.spec.FieldSpec`
(one value per active cell of PORO, PERMX, ...; its prior), any other entry a scalar
:class:`~hmcore.model.parameters.Parameter`; :data:`ParameterEntry` tells them apart by
``kind`` alone, so that an entry's errors are those of its own model. The ``[ensemble]``
section is an :class:`~hmcore.fields.ensemble.EnsembleSpec`. For example::

    [[parameters]]
    name = "poro"
    kind = "field"
    keyword = "PORO"
    high = 0.35
    [parameters.prior]
    source = "geostatistical"
    seed = 11
    variogram = { model = "spherical", ranges = [2000.0, 800.0, 5.0], azimuth = [110.0, 170.0] }
    zones = [{ layers = [1, 1], mean = 0.22, std = 0.04 },
             { layers = [2, 5], mean = 0.17, std = 0.05 }]

    [[parameters]]
    name = "permx"
    kind = "field"
    keyword = "PERMX"             # log10 space (permeability); copies = ["PERMY"] writes both
    prior = { source = "relation", from = "poro", intercept = 0.77, slope = 9.02, seed = 12 }

    [ensemble]
    size = 100
    weights = [4, 2, 1]

:func:`field_problems` checks the fields against each other, against the deck's grid (the
deck OPM has already parsed for :class:`~hmcore.eclipse.deck_info.DeckInfo`, not parsed again)
and against the user's realisations, and names every problem by the case file and the key of
the entry (``case.toml key 'parameters.3.prior.zones.1'``), all at once, before any run.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Annotated, Any, get_args, get_origin

from pydantic import BaseModel, Discriminator, Tag, TypeAdapter, ValidationError

from hmcore.eclipse.deck_info import ParsedDeck
from hmcore.errors import CaseError, Problem
from hmcore.fields.deck_edits import copy_problems, grid_copies, grid_scalings, scaling_problems
from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.fieldset import field_set_problems
from hmcore.fields.spec import (
    CosimulationPrior,
    FieldSpec,
    FilesPrior,
    GeostatisticalPrior,
    RelationPrior,
)
from hmcore.model.parameters import Parameter, ParameterKind
from hmcore.model.validation import did_you_mean


def entry_kind(entry: Any) -> str:
    """The tag of a ``[[parameters]]`` entry: ``"field"`` when its kind is ``"field"``, else
    ``"scalar"`` (a table without a kind, or with another, is a scalar parameter, whose own
    model then states what is wrong)."""
    kind = entry.get("kind") if isinstance(entry, dict) else getattr(entry, "kind", None)
    return "field" if kind == "field" else "scalar"


ParameterEntry = Annotated[
    Annotated[FieldSpec, Tag("field")] | Annotated[Parameter, Tag("scalar")],
    Discriminator(entry_kind)]
"""One ``[[parameters]]`` table: a field or a scalar parameter, by its kind."""

ENTRY_MODELS: dict[str, type[BaseModel]] = {"field": FieldSpec, "scalar": Parameter}
PRIOR_MODELS: dict[str, type[BaseModel]] = {
    "geostatistical": GeostatisticalPrior, "relation": RelationPrior,
    "cosimulation": CosimulationPrior, "files": FilesPrior}
ENTRY_TAGS = frozenset(ENTRY_MODELS) | frozenset(PRIOR_MODELS)
"""The discriminators' tags pydantic puts into an error's location
(``parameters.1.field.prior.geostatistical.zones.0``); the case file has no such key."""

_ENTRY = TypeAdapter(ParameterEntry)
_FIELD_WHERE = re.compile(r"field '(?P<name>[^']*)'(?: zone (?P<zone>.+)| (?P<key>prior\.\w+))?")


def valid_entries(raw: Any) -> list[tuple[int, Parameter | FieldSpec]]:
    """The entries of a ``[[parameters]]`` list that are valid by themselves, with their
    index in the list (used when the file has problems elsewhere, so that the valid
    parameters are still checked against the deck in the same pass)."""
    valid = []
    for i, item in enumerate(raw if isinstance(raw, list) else []):
        try:
            valid.append((i, _ENTRY.validate_python(item)))
        except ValidationError:
            continue
    return valid


def ensemble_size(spec: EnsembleSpec | None, raw: Any) -> int | None:
    """The ensemble size a files prior is checked against: the section's when it is valid,
    else its ``size`` key when that is valid by itself, the default when the section gives
    none, and None (count not checked) when the size itself is wrong."""
    if spec is not None:
        return spec.size
    size = raw.get("size", EnsembleSpec().size) if isinstance(raw, dict) else EnsembleSpec().size
    return size if type(size) is int and size >= 2 else None


def entry_choices(loc: tuple) -> list[str]:
    """The keys allowed where an unknown key of a ``[[parameters]]`` entry sits (``loc`` is
    pydantic's location, tags included): the entry's own model by its kind, nested tables
    (``prior``, ``zones``, ``variogram``) followed by name."""
    model: type[BaseModel] | None = None
    for item in loc[1:-1]:
        if isinstance(item, int):
            continue
        if item in ENTRY_MODELS or item in PRIOR_MODELS:
            model = {**ENTRY_MODELS, **PRIOR_MODELS}[item]
            continue
        info = model.model_fields.get(item) if model is not None else None
        model = _model_in(info.annotation) if info is not None else None
    if model is None:
        return []
    return [info.alias or name for name, info in model.model_fields.items()]


def kind_hint(given: Any) -> str:
    """The fix for an unknown ``kind`` of a parameter: the kinds, ``"field"`` among them."""
    kinds = [k.value for k in ParameterKind] + ["field"]
    return f"use one of {kinds}" + did_you_mean(given, kinds)


def resolved(field: FieldSpec, folder_of: Callable[[str], Path]) -> FieldSpec:
    """``field`` with its files prior's folder made absolute by ``folder_of`` (relative to
    the case file: resolved once, as the deck's and the history's paths are)."""
    if not isinstance(field.prior, FilesPrior):
        return field
    return field.model_copy(update={"prior": field.prior.model_copy(
        update={"folder": str(folder_of(field.prior.folder).resolve())})})


def field_problems(case_file: Path, fields: Sequence[tuple[int, FieldSpec]],
                   parsed: ParsedDeck | None, size: int | None,
                   folder_of: Callable[[str], Path]) -> list[Problem]:
    """Every problem of the case's fields, named by ``case_file`` and the entry's key.

    ``fields`` are the valid field entries with their index in ``[[parameters]]``. Checked:
    the fields together (:func:`~hmcore.fields.fieldset.field_set_problems`: names, written
    keywords and seeds unique, ``from`` naming a field, no cycle); with the deck parsed
    (``parsed``; None when it could not be), the priors against its grid (keyword defined,
    zones inside the grid and covering its active cells once:
    :func:`~hmcore.fields.zones.prior_problems`; no GRID ``COPY`` from a field's keyword to
    one no field writes, no GRID ``MULTIPLY`` of a keyword a field writes:
    :mod:`hmcore.fields.deck_edits`) and a files prior's
    realisations (the folder
    from ``folder_of``, relative to the case file; ``size`` files at least, each with the
    keyword for every cell or active cell, values in range:
    :func:`~hmcore.fields.realisations.read_realisations`; ``size`` None: the files there)."""
    # these import opm.io: keeps start-up fast (reading a case without fields never loads it)
    from hmcore.fields.grid import from_parsed
    from hmcore.fields.realisations import read_realisations, realisation_files
    from hmcore.fields.zones import prior_problems

    index: dict[str, int] = {}
    for i, f in fields:
        index.setdefault(f.name, i)
    unique = [f for i, f in fields if index[f.name] == i]  # a repeated name: reported already
    by_name = {f.name: f for f in unique}

    def located(problems: list[Problem]) -> list[Problem]:
        return [_located(p, case_file, index, by_name) for p in problems]

    problems = located(field_set_problems(unique))
    if parsed is None or not unique:
        return problems
    try:
        grid = from_parsed(parsed.deck, parsed.state, str(parsed.path))
    except CaseError as exc:  # active cells or cell centres not known
        return problems + exc.problems
    problems += located(prior_problems(unique, grid))
    problems += located(copy_problems(unique, grid_copies(parsed.deck), parsed.path.name))
    problems += located(scaling_problems(unique, grid_scalings(parsed.deck), parsed.path.name))
    for f in unique:
        if not isinstance(f.prior, FilesPrior):
            continue
        at = f"{case_file} key 'parameters.{index[f.name]}.prior"
        try:
            folder = folder_of(f.prior.folder)
        except ValueError as exc:
            problems.append(Problem(f"{at}.folder'", str(exc), "give a plain path, relative "
                                    "to the case file or absolute"))
            continue
        count = size if size is not None else (
            len(realisation_files(f.prior, folder)) if folder.is_dir() else 1)
        _, found = read_realisations(f, folder, grid, count)
        problems += [_realisation_problem(p, at, folder) for p in found]
    return problems


def _located(p: Problem, case_file: Path, index: dict[str, int],
             by_name: dict[str, FieldSpec]) -> Problem:
    """A problem named ``field '<name>'`` (``... zone <label>``, ``... prior.folder``) or
    ``fields`` as the case file's key: ``case.toml key 'parameters.3.prior.zones.1'``."""
    match = _FIELD_WHERE.fullmatch(p.where)
    if p.where == "fields":
        return Problem(f"{case_file} key 'parameters'", p.what, p.fix)
    if match is None or match["name"] not in index:
        return Problem(f"{case_file} {p.where}", p.what, p.fix)
    key = f"parameters.{index[match['name']]}"
    if match["zone"]:
        zones = getattr(by_name[match["name"]].prior, "zones", ())
        j = next((j for j, z in enumerate(zones) if z.label() == match["zone"]), None)
        key += f".prior.zones.{j}" if j is not None else ".prior.zones"
        return Problem(f"{case_file} key '{key}' ({match['zone']})", p.what, p.fix)
    if match["key"]:
        key += f".{match['key']}"
    return Problem(f"{case_file} key '{key}'", p.what, p.fix)


def _realisation_problem(p: Problem, at: str, folder: Path) -> Problem:
    """A problem of the user's realisations, named by the entry's key and the file."""
    if p.where.endswith("prior.folder"):
        return Problem(f"{at}.folder'", p.what, p.fix)
    if p.where == str(folder):
        return Problem(f"{at}.folder' ({folder})", p.what, p.fix)
    return Problem(f"{at}' file {p.where}", p.what, p.fix)


def _model_in(annotation: Any) -> type[BaseModel] | None:
    """The one model inside a field's annotation (``Zone`` in ``tuple[Zone, ...]``,
    ``Variogram`` in ``Variogram | None``); None when there is none or several (a union of
    priors is resolved by its tag instead)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    if get_origin(annotation) is Annotated:
        return _model_in(get_args(annotation)[0])
    found = {m for a in get_args(annotation) if (m := _model_in(a)) is not None}
    return found.pop() if len(found) == 1 else None

