"""An ensemble as a table, and one member as a simulator run.

The table: an ensemble ``X`` ``(members, parameters)`` float32 in update space
(:class:`~hmcore.fields.layout.Layout`'s column order) is stored with one *row* per
parameter and one *column* per member (``m0000``, ``m0001``, ...), beside ``parameter`` (the
field's or scalar's name) and ``cell`` (the active cell's index in the field, -1 for a
scalar). A member's run then reads its own column only (Parquet is columnar), whatever the
grid's size. A member left out of an update is a column of NaN.

The run: :class:`MemberSimulator` (and :class:`LatentSimulator`, whose fields are the latent
basis's at a call's coefficients) wraps the case's simulator. Given the per-run deck hmflow
has written (the scalar parameters applied, INCLUDE paths absolute:
:mod:`hmcore.model.run_deck`), it writes the member's fields as a GRDECL file in the run
directory (:func:`hmcore.fields.grdecl.write_member`: physical values, truncated to the
bounds) and inserts an ``INCLUDE`` of it at the end of the deck's GRID section, just before
the section that follows (EDIT or PROPS): after every GRID edit of the deck (``COPY``,
``MULTIPLY``, ``EQUALS``...), so the member's values are the ones the simulator uses. Then
the wrapped simulator runs the deck. Nothing here starts a process itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from hmcore.eclipse.deck_info import SECTION_NAMES
from hmcore.eclipse.lexer import split_blocks
from hmcore.errors import CaseError, Problem
from hmcore.fields.grdecl import write_member
from hmcore.fields.grid import FieldGrid
from hmcore.fields.latent import LatentBasis
from hmcore.fields.layout import Layout
from hmcore.fields.spec import FieldSpec

INCLUDE_NAME = "FIELDS.GRDECL"
"""The member's include file, in its run directory."""


def member_column(member: int) -> str:
    """The table's column of member ``member`` (0-based): ``m0007``."""
    return f"m{member:04d}"


def ensemble_table(X: np.ndarray, layout: Layout) -> pd.DataFrame:
    """``X`` ``(members, layout.size)`` as the stored table (see the module's docstring)."""
    X = np.asarray(X, np.float32)
    if X.ndim != 2 or X.shape[1] != layout.size:
        raise ValueError(f"X must have shape (members, {layout.size}), got {X.shape}")
    names = [n for n in layout.fields for _ in range(layout.n_active)] + list(layout.scalars)
    cells = np.concatenate([np.tile(np.arange(layout.n_active, dtype=np.int32),
                                    len(layout.fields)),
                            np.full(len(layout.scalars), -1, np.int32)])
    columns: dict[str, Any] = {"parameter": pd.Categorical(names), "cell": cells}
    columns.update((member_column(m), X[m]) for m in range(X.shape[0]))
    return pd.DataFrame(columns)


def ensemble_matrix(table: pd.DataFrame, layout: Layout) -> np.ndarray:
    """The stored table back as ``X`` ``(members, layout.size)`` float32; ValueError when its
    rows are not ``layout``'s."""
    _check_rows(table["parameter"].astype(str).to_numpy(), table["cell"].to_numpy(), layout)
    members = sorted(c for c in table.columns if c.startswith("m") and c[1:].isdigit())
    return np.stack([table[c].to_numpy(np.float32) for c in members]) if members else \
        np.zeros((0, layout.size), np.float32)


def read_member(path: Path | str, member: int, layout: Layout) -> np.ndarray:
    """Member ``member``'s row of the ensemble stored at ``path`` ``(layout.size,)`` float32,
    reading only its column (and the row labels, to check them against ``layout``)."""
    table = pq.read_table(path, columns=["parameter", "cell", member_column(member)])
    _check_rows(np.asarray(table.column("parameter").to_pylist(), dtype=object),
                table.column("cell").to_numpy(), layout)
    return table.column(member_column(member)).to_numpy().astype(np.float32)


def _check_rows(names: np.ndarray, cells: np.ndarray, layout: Layout) -> None:
    expected = ensemble_table(np.zeros((0, layout.size), np.float32), layout)
    if (len(names) != layout.size or not np.array_equal(cells, expected["cell"].to_numpy())
            or list(names) != list(expected["parameter"].astype(str))):
        raise ValueError(f"the stored ensemble's rows are not the layout's (fields "
                         f"{list(layout.fields)} of {layout.n_active} cells, scalars "
                         f"{list(layout.scalars)}); it has {len(names)} rows")


def insert_grid_include(text: str, include: Path, keywords: frozenset[str]) -> str:
    """``text`` (a deck) with ``INCLUDE 'include' /`` at the end of its GRID section: before
    the first section keyword after ``GRID``. CaseError when the deck's GRID section does not
    end in this file (its end is in an include hmflow did not copy into the deck)."""
    blocks = split_blocks(text, set(keywords) | set(SECTION_NAMES))
    out: list[str] = []
    section, done = None, False
    for block in blocks:
        if block.keyword in SECTION_NAMES:
            if section == "GRID" and not done:
                out.append(f"-- the ensemble member's fields, added by hmflow\nINCLUDE\n"
                           f"  '{include}' /\n\n")
                done = True
            section = block.keyword
        out.extend(block.lines)
    if not done:
        raise CaseError([Problem(str(include.parent), "the deck has no section keyword (EDIT "
                                 "or PROPS) after GRID in its main file, so hmflow cannot place "
                                 "the member's fields after the deck's own GRID keywords",
                                 "keep the keyword that ends GRID (EDIT or PROPS) in the main "
                                 "deck file")])
    return "".join(out)


@dataclass(frozen=True)
class MemberSimulator:
    """The case's simulator (``inner``, anything with ``run(deck, run_dir)`` and ``name``),
    running member ``member`` of the ensemble stored at ``ensemble``: its fields written to
    :data:`INCLUDE_NAME` in the run directory and included at the end of GRID (see the
    module's docstring). Holds paths and the grid, not the member's values, so it is small to
    send to a worker; the values are read when the run starts."""

    inner: Any
    ensemble: Path
    member: int
    fields: tuple[FieldSpec, ...]
    grid: FieldGrid
    layout: Layout
    keywords: frozenset[str]

    @property
    def name(self) -> str:
        return getattr(self.inner, "name", "simulator")

    def values(self) -> dict[str, np.ndarray]:
        """{field name: update-space values ``(n_active,)``} of this member."""
        row = read_member(self.ensemble, self.member, self.layout)
        fields, _ = self.layout.split(row[None, :])
        return {name: values[0] for name, values in fields.items()}

    def run(self, deck: Path, run_dir: Path):
        return run_with_fields(self.inner, deck, run_dir, self.fields, self.values(), self.grid,
                               self.keywords, f"member {self.member} of {self.ensemble}")


@dataclass(frozen=True)
class LatentSimulator:
    """The case's simulator (``inner``) running the fields that the coefficients ``z`` of the
    latent basis stored at ``basis`` make (:class:`hmcore.fields.latent.LatentBasis`, in
    ``layout``'s field columns), included at the end of GRID as a member's are. One per call:
    :meth:`bound` gives it the call's values. Holds paths and numbers, not the basis."""

    inner: Any
    basis: Path
    fields: tuple[FieldSpec, ...]
    grid: FieldGrid
    layout: Layout
    keywords: frozenset[str]
    z: tuple[float, ...] = ()

    @property
    def name(self) -> str:
        return getattr(self.inner, "name", "simulator")

    def bound(self, z) -> LatentSimulator:
        """This simulator for coefficients ``z`` (``(k,)``, the basis's mode order)."""
        return replace(self, z=tuple(float(v) for v in z))

    def values(self) -> dict[str, np.ndarray]:
        """{field name: update-space values ``(n_active,)``} of ``z``."""
        table = pq.read_table(self.basis).to_pandas()
        _check_rows(table["parameter"].astype(str).to_numpy(), table["cell"].to_numpy(),
                    self.layout)
        doc = LatentBasis.from_table(table, float("nan"), 0)
        row = doc.fields(np.asarray(self.z, float)).astype(np.float32)
        fields, _ = self.layout.split(row[None, :])
        return {name: values[0] for name, values in fields.items()}

    def run(self, deck: Path, run_dir: Path):
        return run_with_fields(self.inner, deck, run_dir, self.fields, self.values(), self.grid,
                               self.keywords, f"latent coefficients of {self.basis}: "
                               + " ".join(f"{v:.6g}" for v in self.z))


def run_with_fields(inner, deck: Path, run_dir: Path, fields: tuple[FieldSpec, ...],
                    values: dict[str, np.ndarray], grid: FieldGrid, keywords: frozenset[str],
                    header: str):
    """Write ``values`` (update space, per field) to :data:`INCLUDE_NAME` in ``run_dir``,
    include it at the end of the deck's GRID section and run the deck with ``inner``."""
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    include = write_member(run_dir / INCLUDE_NAME, fields, values, grid, header=header)
    deck = Path(deck)
    deck.write_text(insert_grid_include(deck.read_text(errors="replace"), include, keywords))
    return inner.run(deck, run_dir)


def scalar_prior(size: int, names: Sequence[str], seed: int) -> np.ndarray:
    """Prior members of scalar parameters in an ensemble ``(size, len(names))`` float32:
    uniform in their scaled coordinates [-1, 1] (the parameter's box; log-scaled parameters
    uniform in log), from ``default_rng([seed, SCALAR_STREAM])``."""
    rng = np.random.default_rng([seed, SCALAR_STREAM])
    return rng.uniform(-1.0, 1.0, (size, len(names))).astype(np.float32)


SCALAR_STREAM = 2**31 - 1
"""The random stream of the scalars' prior: apart from iteration i's ``[seed, i]``."""
