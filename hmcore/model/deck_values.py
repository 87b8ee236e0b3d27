"""The deck's own values of a case's parameters: the base model as given, before any
calibration (multipliers 1, shifts 0, skins as completed in COMPDAT), and the deck facts they
are read from (records of a few keywords, include files followed; each well's mean skin).

The floor run of a benchmark without a known truth, the "before" of a report and the start
of a diagnosis are all this model.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hmcore.eclipse.deck_info import DeckInfo
from hmcore.eclipse.includes import resolve_include
from hmcore.eclipse.lexer import expand_repeats, include_target, records, split_blocks
from hmcore.model.parameters import ParameterSpace

MAX_INCLUDE_BYTES = 2 ** 21
"""An include file larger than this (2 MiB: a grid or property array) is not read for the
few keywords :func:`deck_blocks` looks for."""


def deck_blocks(info: DeckInfo) -> dict[str, list[list[str]]]:
    """Records of selected keywords in the deck (include files followed)."""
    wanted = {"AQUCT", "AQUFETP", "COMPDAT", "SWOF", "SWFN", "SGOF", "SGFN", "EQUIL"}
    found: dict[str, list[list[str]]] = {}
    seen: set[Path] = set()

    def visit(path: Path) -> None:
        if path in seen or not path.is_file():
            return
        seen.add(path)
        if path.stat().st_size > MAX_INCLUDE_BYTES and path != info.path:
            return
        for block in split_blocks(path.read_text(errors="replace"), info.keyword_names):
            if block.keyword == "INCLUDE":
                target = include_target(block)
                if target:
                    visit(resolve_include(target, path, info.path.parent))
            elif block.keyword in wanted:
                found.setdefault(block.keyword, []).extend(
                    [expand_repeats(r) for r in records(block.body)])

    visit(info.path)
    return found


def deck_skins(info: DeckInfo) -> dict[str, float]:
    """Mean COMPDAT skin (item 11, default 0) of each well's connections in the deck."""
    skins: dict[str, list[float]] = {}
    for rec in deck_blocks(info).get("COMPDAT", []):
        well = rec[0].strip("'\"")
        try:
            s = float(rec[10]) if len(rec) > 10 and rec[10] != "1*" else 0.0
        except ValueError:
            s = 0.0
        skins.setdefault(well, []).append(s)
    return {w: sum(v) / len(v) for w, v in skins.items()}


def base_values(info: DeckInfo, space: ParameterSpace) -> dict[str, float]:
    """The base model as given, in ``space``: multipliers 1, shifts 0, each skin parameter the
    mean deck skin (COMPDAT item 11) of its wells (default: the producers), clipped to its
    bounds."""
    skins = deck_skins(info)
    out = {}
    for p in space.parameters:
        if p.kind == "skin":
            wells = p.wells or tuple(info.producers)
            v = float(np.mean([skins.get(w, 0.0) for w in wells])) if wells else 0.0
        elif (p.kind == "relperm" and p.mode == "endpoint") or p.kind == "latent":
            v = 0.0  # a shift: none; a latent coefficient: the prior's mean
        else:
            v = 1.0
        out[p.name] = float(np.clip(v, p.low, p.high))
    return out
