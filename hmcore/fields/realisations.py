"""A prior the user brings: one GRDECL file per member (ERT's way), read and checked at once.

The files are those of the prior's ``folder`` matching its ``pattern``, in natural order
(``poro_2`` before ``poro_10``); member ``m`` is the ``m``-th. Every file is read and every
problem reported together, as :class:`~hmcore.errors.Problem` objects naming the file: too few
files, a file OPM's parser refuses, the keyword missing, a value count that is neither the
grid's cells nor its active cells, values that are not finite, permeability that is not
positive, porosity or net-to-gross outside [0, 1]. The members come back in update space,
``(size, n_active)`` float32, only when nothing is wrong.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from hmcore.errors import Problem
from hmcore.fields.grdecl import GrdeclError, read_grdecl
from hmcore.fields.grid import FieldGrid
from hmcore.fields.spec import FRACTIONS, PERMEABILITY, FieldSpec, FilesPrior
from hmcore.fields.transform import to_update_space


def natural_key(path: Path) -> list:
    """Sort key putting ``poro_2`` before ``poro_10``."""
    return [int(part) if part.isdigit() else part.lower()
            for part in re.split(r"(\d+)", path.name)]


def realisation_files(prior: FilesPrior, folder: Path) -> list[Path]:
    """The files of ``folder`` matching ``prior.pattern``, in natural order."""
    return sorted((p for p in folder.glob(prior.pattern) if p.is_file()), key=natural_key)


def read_realisations(field: FieldSpec, folder: Path | str, grid: FieldGrid,
                      size: int) -> tuple[np.ndarray | None, list[Problem]]:
    """The first ``size`` realisations of ``field`` (whose prior is ``source = "files"``)
    from ``folder`` (the prior's folder, resolved by the caller), and every problem found.

    Returns ``(members, [])`` with members ``(size, n_active)`` float32 in update space, or
    ``(None, problems)``."""
    prior = field.prior
    if not isinstance(prior, FilesPrior):
        raise TypeError(f"field '{field.name}' has prior.source = {prior.source!r}, not 'files'")
    folder = Path(folder)
    keyword = (prior.keyword or field.keyword).upper()
    if not folder.is_dir():
        return None, [Problem(f"field '{field.name}' prior.folder", f"{folder} is not a folder",
                              "give the folder of the realisations, relative to the case file")]
    files = realisation_files(prior, folder)
    problems: list[Problem] = []
    if len(files) < size:
        problems.append(Problem(str(folder), f"the ensemble has {size} members but "
                                f"{len(files)} file(s) match {prior.pattern!r}",
                                f"give one file per member, or lower ensemble.size to "
                                f"{len(files)}"))
    members = np.zeros((size, grid.n_active), np.float32)
    for m, path in enumerate(files[:size]):
        values = _member(path, keyword, grid, problems)
        if values is None:
            continue
        before = len(problems)
        problems.extend(_value_problems(path, keyword, field, values, grid))
        if len(problems) == before:
            members[m] = to_update_space(values, field)
    return (None, problems) if problems else (members, [])


def _member(path: Path, keyword: str, grid: FieldGrid,
            problems: list[Problem]) -> np.ndarray | None:
    """The active cells' values of ``keyword`` in ``path`` (None after adding a problem)."""
    try:
        arrays = read_grdecl(path)
    except GrdeclError as exc:
        problems.append(Problem(str(path), f"OPM's parser refuses the file: {exc}",
                                "fix the keyword and line named"))
        return None
    if keyword not in arrays:
        problems.append(Problem(str(path), f"has no {keyword}; it has "
                                f"{sorted(arrays) or 'no keyword'}",
                                f"write the realisation as keyword {keyword}"))
        return None
    values = np.asarray(arrays[keyword], np.float64)
    if values.size == grid.n_total:
        return values[grid.active]
    if values.size == grid.n_active:
        return values
    problems.append(Problem(str(path), f"{keyword} has {values.size} values; the grid "
                            f"{'x'.join(map(str, grid.dims))} has {grid.n_total} cells, "
                            f"{grid.n_active} of them active",
                            "give a value for every cell, or for every active cell"))
    return None


def _value_problems(path: Path, keyword: str, field: FieldSpec, values: np.ndarray,
                    grid: FieldGrid) -> list[Problem]:
    """What is wrong with the active cells' ``values`` (empty when nothing)."""
    bad = ~np.isfinite(values)
    rule = "finite"
    if not bad.any() and (keyword in PERMEABILITY or field.in_log):
        bad, rule = ~(values > 0), "> 0 (permeability, or a field in log space)"
    elif not bad.any() and keyword in FRACTIONS:
        bad, rule = ~((values >= 0) & (values <= 1)), "in [0, 1] (a fraction)"
    if not bad.any():
        return []
    first = int(np.flatnonzero(bad)[0])
    return [Problem(str(path), f"{keyword} must be {rule} in every active cell; "
                    f"{int(bad.sum())} are not, e.g. {float(values[first])!r} in cell (i, j, k) = "
                    f"{tuple(grid.ijk[first].tolist())}", "correct the realisation")]
