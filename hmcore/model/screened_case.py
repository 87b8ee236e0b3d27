"""The case file a screening writes (``hmflow screen``): the old case with only the parameters
that matter switched on, beside the old file and never over any existing file.

The old file is read with tomlkit, so that its comments and every other section stay as they
are. Its ``[[parameters]]`` tables are kept when chosen; the others are left out and written
back as comments (so that switching one on again is removing the ``#``), as are a
``kind = "field"`` entry's (a screening ranks the scalar ones only: fields are kept). A case
without ``[[parameters]]`` (the five reference parameters by default) gets the chosen ones
written out. Relative paths stay valid: the new file sits in the old one's folder.
"""

from __future__ import annotations

from pathlib import Path

import tomlkit

from hmcore.model.parameters import Parameter

SCREENED_SUFFIX = ".screened"
"""``case.toml`` -> ``case.screened.toml`` (then ``case.screened-2.toml``, ...)."""


def free_name(old: Path) -> Path:
    """The first of ``NAME.screened.toml``, ``NAME.screened-2.toml``, ... beside ``old`` that
    does not exist."""
    stem, n = old.stem + SCREENED_SUFFIX, 1
    while True:
        candidate = old.with_name(f"{stem}{'' if n == 1 else f'-{n}'}{old.suffix or '.toml'}")
        if not candidate.exists():
            return candidate
        n += 1


def screened_text(old_text: str, parameters: tuple[Parameter, ...], chosen: tuple[str, ...],
                  header: list[str]) -> str:
    """The new case file's text: ``old_text`` with only the ``chosen`` scalar parameters on
    (``parameters``: the case's scalar parameters, used when the file lists none), ``header``
    comment lines first."""
    doc = tomlkit.parse(old_text)
    new = tomlkit.document()
    for line in header:
        new.add(tomlkit.comment(line))
    new.add(tomlkit.nl())
    entries = doc.get("parameters")
    dropped_text: list[str] = []
    for key, value in doc.body:
        if key is None or key.key != "parameters":
            if key is None:
                new.add(value)
            else:
                new.append(key, value)
    kept = tomlkit.aot()
    if entries is None:
        for p in parameters:
            if p.name in chosen:
                kept.append(tomlkit.item(p.model_dump(mode="json", exclude_defaults=True)))
            else:
                dropped_text.append(_commented({"parameters": [
                    p.model_dump(mode="json", exclude_defaults=True)]}))
    else:
        for table in entries:
            if table.get("kind") == "field" or table.get("name") in chosen:
                kept.append(table)
            else:
                dropped_text.append(_commented({"parameters": [table.unwrap()]}))
    if len(kept):
        new.append("parameters", kept)
    text = tomlkit.dumps(new)
    if dropped_text:
        text += ("\n# screened out (switch one on again by removing its '#'):\n"
                 + "\n".join(dropped_text))
    return text


def _commented(data: dict) -> str:
    return "\n".join(f"# {line}" if line else "#"
                     for line in tomlkit.dumps(data).strip().splitlines()) + "\n"


def write_screened(old: Path, parameters: tuple[Parameter, ...], chosen: tuple[str, ...],
                   header: list[str]) -> Path:
    """Write the new case beside ``old`` under :func:`free_name` (exclusive creation: an
    existing file is never overwritten); returns its path."""
    text = screened_text(old.read_text(encoding="utf-8"), parameters, chosen, header)
    while True:
        path = free_name(old)
        try:
            with path.open("x", encoding="utf-8") as f:
                f.write(text)
            return path
        except FileExistsError:  # taken between the look and the write: the next name
            continue
