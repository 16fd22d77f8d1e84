"""Short excerpts of user content for one-line error messages: a broken 250 MB file must not print a 1 GB line."""
from __future__ import annotations

from typing import Any

EXCERPT_CHARS = 80  # longest excerpt of a file's content or an exception's text quoted in a message


def one_line(text: Any, limit: int = EXCERPT_CHARS) -> str:
    """``text`` with its whitespace collapsed to single spaces, cut to ``limit`` characters."""
    line = " ".join(str(text)[:4 * limit].split())
    return line if len(line) <= limit else line[:limit - 3] + "..."


def excerpt(value: str, limit: int = EXCERPT_CHARS) -> str:
    """``repr`` of ``value``, cut to ``limit`` characters with its full length named."""
    if len(value) <= limit:
        return repr(value)
    return f"{value[:limit]!r}... ({len(value)} characters)"
