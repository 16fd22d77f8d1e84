"""A GitHub markdown table from header and rows of text: the one formatter of the run report, the sweep summary
and the verification studies' own reports (so that neither stage imports the other for it)."""
from __future__ import annotations

from typing import Optional, Sequence


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]],
                   best: Optional[Sequence[Sequence[bool]]] = None) -> str:
    """A GitHub markdown table; cells flagged in ``best`` are bold."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for i, row in enumerate(rows):
        cells = [f"**{c}**" if best is not None and best[i][j] else str(c) for j, c in enumerate(row)]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)
