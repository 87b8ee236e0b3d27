"""The files a deck reads: the main file and every file it INCLUDEs, recursively, wherever
they live (the one INCLUDE resolver of hmflow; OPM's rule: a relative path is looked up from
the main deck's folder, then from the including file's folder)."""

from __future__ import annotations

from pathlib import Path

from hmcore.eclipse.lexer import include_target, split_blocks


def resolve_include(target: str, including_file: Path, main_dir: Path) -> Path:
    """The file an ``INCLUDE 'target' /`` in ``including_file`` names (it may not exist)."""
    path = Path(target)
    if path.is_absolute():
        return path
    for base in (main_dir, including_file.parent):
        if (base / path).exists():
            return (base / path).resolve()
    return (main_dir / path).resolve()


def deck_files(main: Path) -> list[Path]:
    """``main`` and every existing file it INCLUDEs, recursively, each once (a cycle is
    followed once), in the order first met. Missing includes and cycles are reported (with
    their line) by :func:`hmcore.eclipse.deck_info.missing_includes`, which resolves them here too."""
    main = Path(main).resolve()
    seen: list[Path] = []
    stack = [main]
    while stack:
        file = stack.pop()
        if file in seen or not file.is_file():
            continue
        seen.append(file)
        text = file.read_text(errors="replace")
        found = [resolve_include(t, file, main.parent) for t in
                 (include_target(b) for b in split_blocks(text, {"INCLUDE"})
                  if b.keyword == "INCLUDE") if t]
        stack.extend(reversed(found))
    return seen
