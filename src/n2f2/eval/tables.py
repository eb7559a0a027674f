"""Markdown tables and their number formats, shared by every report of ``n2f2 eval`` and the bench.

Scores are shown in percent with one decimal, as the paper's tables are. A leaf: the report
modules (:mod:`.reports`, :mod:`.budget`, :mod:`.protocol3d`, ...) all import it, it imports none.
"""

from __future__ import annotations

import math
import numbers
from typing import Any, Optional, Sequence

import numpy as np


def fmt(value: object, digits: int = 1, percent: bool = False) -> str:
    """Numbers as text: percent (x100) with ``digits`` decimals, NaN as "n/a", None as "-"."""
    if value is None:
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)) and not percent:
        return str(int(value))
    if isinstance(value, numbers.Real):
        v = float(value)
        if math.isnan(v):
            return "n/a"
        return f"{100 * v:.{digits}f}" if percent else f"{v:.{digits}f}"
    return str(value)


def pct(v: Any) -> str:
    """A score in percent with one decimal (:func:`fmt`)."""
    return fmt(v, percent=True)


def _cell(text: object) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def markdown_table(
    headers: Sequence[str],
    rows: Sequence[Sequence[object]],
    align: Optional[Sequence[str]] = None,  # per column "l" | "r" | "c"; default l then r
) -> str:
    """A GitHub Markdown table; cells are str()-ed (floats should be formatted by the caller),
    and '|' in a cell is escaped."""
    n = len(headers)
    if any(len(r) != n for r in rows):
        raise ValueError(f"every row needs {n} cells")
    align = list(align) if align is not None else ["l"] + ["r"] * (n - 1)
    rule = {"l": ":---", "r": "---:", "c": ":---:"}
    lines = ["| " + " | ".join(_cell(h) for h in headers) + " |", "| " + " | ".join(rule[a] for a in align) + " |"]
    lines += ["| " + " | ".join(_cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"
