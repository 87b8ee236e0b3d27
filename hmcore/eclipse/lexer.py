"""A small lexer for Eclipse-format decks: comments, quotes, ``N*`` repeats, ``/`` records.

It only splits text into keyword blocks and records; which words are keywords comes from OPM's
parser (:class:`hmcore.eclipse.deck_info.DeckInfo`), so data that looks like a keyword is not mistaken.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_KEYWORD_RE = re.compile(r"^([A-Z][A-Z0-9_+-]{0,7})(?:\s|$)")


def strip_comment(line: str) -> str:
    """The part of ``line`` before a ``--`` comment that is not inside quotes."""
    if "--" not in line:  # most data lines: nothing to scan
        return line
    if "'" not in line and '"' not in line:
        return line[:line.index("--")]
    quote = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "-" and line.startswith("--", i):
            return line[:i]
    return line


def tokenize(text: str) -> list[str]:
    """Tokens of record text: quoted strings keep their quotes; ``/`` outside quotes is a token."""
    tokens: list[str] = []
    for raw in text.splitlines():
        line = strip_comment(raw)
        i, n = 0, len(line)
        while i < n:
            ch = line[i]
            if ch.isspace():
                i += 1
            elif ch == "/":
                tokens.append("/")
                i += 1
            elif ch in "'\"":
                end = line.find(ch, i + 1)
                end = n - 1 if end < 0 else end
                tokens.append(line[i:end + 1])
                i = end + 1
            else:
                j = i
                while j < n and not line[j].isspace() and line[j] not in "/'\"":
                    j += 1
                tokens.append(line[i:j])
                i = j
    return tokens


def expand_repeats(tokens: list[str]) -> list[str]:
    """``3*`` -> three ``1*`` defaults; ``2*5.0`` -> ``5.0 5.0``."""
    out: list[str] = []
    for tok in tokens:
        m = re.fullmatch(r"(\d+)\*(.*)", tok)
        if m and not tok.startswith("'"):
            out.extend([m.group(2) or "1*"] * int(m.group(1)))
        else:
            out.append(tok)
    return out


@dataclass
class Block:
    """A keyword and the lines that follow it up to the next keyword (comments included)."""

    keyword: str
    lines: list[str] = field(default_factory=list)

    @property
    def body(self) -> str:
        return "".join(self.lines[1:])


def split_blocks(text: str, known_keywords: set[str]) -> list[Block]:
    """Split a deck file into keyword blocks; text before the first keyword is block ``""``.

    A line starts a keyword when its first token (at any indentation, outside comments) is one
    of ``known_keywords`` and the line holds no record terminator ``/``.
    """
    blocks = [Block("")]
    for line in text.splitlines(keepends=True):
        code = strip_comment(line).strip()
        m = _KEYWORD_RE.match(code)
        if m and "/" not in code and m.group(1) in known_keywords:
            blocks.append(Block(m.group(1), [line]))
        else:
            blocks[-1].lines.append(line)
    return blocks


def records(body: str) -> list[list[str]]:
    """Records of a list keyword (each ended by ``/``, the list ended by an empty record)."""
    out: list[list[str]] = []
    current: list[str] = []
    for tok in tokenize(body):
        if tok == "/":
            if not current:
                break
            out.append(current)
            current = []
        else:
            current.append(tok)
    return out


def include_target(block: Block) -> str | None:
    """The path named by an INCLUDE block (quotes removed), or None if it names none."""
    toks = [t for t in tokenize(block.body) if t != "/"]
    return toks[0].strip("'\"") if toks else None
