"""Text from files made safe to print: names and messages that quote a file's contents become one line, with no
terminal escapes and a bounded length."""

from __future__ import annotations

import difflib
import re
from collections.abc import Callable, Sequence
from typing import Any

# C0 and C1 controls (line breaks, ESC and CSI start terminal escapes), DEL, zero-width and bidi overrides.
_UNPRINTABLE = re.compile(r"[\x00-\x1f\x7f-\x9f\u061c\u200b-\u200f\u2028-\u202e\u2060-\u2069\ufeff]")
MAX_MESSAGE_CHARS = 2000


def printable(message: str) -> str:
    """A message safe to print: control and bidi characters escaped (\\x0a, \\u202e), and at most
    MAX_MESSAGE_CHARS characters: the first 1500 and the last 400 kept (a name from a file may be megabytes).
    """
    message = _UNPRINTABLE.sub(lambda m: _escape(m.group()), message)
    if len(message) > MAX_MESSAGE_CHARS:
        omitted = len(message) - 1900
        message = f"{message[:1500]} [... {omitted} characters omitted ...] {message[-400:]}"
    return message


MAX_NAME_CHARS = 200  # a name longer than this is cut (its start and end kept) in tables and summaries


def safe_name(name: object) -> str:
    """A name from a file (link, joint, frame, file name) as it may be shown on a terminal, inside a line.

    Control characters (C0, C1, DEL), line and paragraph separators, zero-width and bidirectional overrides
    are escaped visibly (\\x0a, \\u202e): a name cannot break a line, colour or clear the terminal, or reorder
    what is printed around it. At most MAX_NAME_CHARS characters are kept (the first 150 and the last 40).
    Every place that prints names uses this (messages use printable, which applies the same escapes).
    """
    text = _UNPRINTABLE.sub(lambda m: _escape(m.group()), str(name))
    if len(text) > MAX_NAME_CHARS:
        text = f"{text[:150]}[... {len(text) - 190} characters ...]{text[-40:]}"
    return text


def terminal_text(text: str) -> str:
    """Text for a terminal whose own line breaks are kept: every other unprintable character is escaped as
    safe_name does (the last defence of the command line's output; names are escaped where they are inserted)."""
    return "\n".join(_UNPRINTABLE.sub(lambda m: _escape(m.group()), line) for line in text.split("\n"))


def _escape(char: str) -> str:
    code = ord(char)
    return f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"


def name_hint(name: object, names: list[str]) -> str:
    """What to say of a name that is not among `names`: "did you mean 'x'?" naming the closest (difflib,
    similarity >= 0.5, up to three), else "valid: " and all of them; names made safe to print."""
    close = [safe_name(c) for c in difflib.get_close_matches(str(name), names, n=3, cutoff=0.5)]
    if close:
        return f"did you mean {' or '.join(repr(c) for c in close)}?"
    return f"valid: {', '.join(safe_name(n) for n in names)}"


def text_table(
    headers: Sequence[str], rows: Sequence[Sequence[Any]], indent: int = 0, *, cell: Callable[[Any], str] = str
) -> str:
    """Left-aligned columns separated by two spaces, each line indented by `indent` spaces and without trailing
    blanks; `cell` turns each cell into its text (the command line passes safe_name: names from files)."""
    cells = [[cell(c) for c in row] for row in [headers, *rows]]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]
    pad = " " * indent
    return "\n".join(pad + "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in cells)
