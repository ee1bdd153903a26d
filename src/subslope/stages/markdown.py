"""Markdown pieces of the campaign's reports (``summary.md`` and the tables beside it)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

__all__ = ["fmt", "md_table"]


def fmt(x, digits: int = 3) -> str:
    """``x`` with ``digits`` decimals; ``n/a`` for None or a non-finite number, ``str(x)``
    for anything that is not a number."""
    try:
        return "n/a" if x is None or not math.isfinite(float(x)) else f"{float(x):.{digits}f}"
    except (TypeError, ValueError):
        return str(x)


def md_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    """A GitHub-flavoured markdown table of ``rows`` (mappings) in ``columns``; floats
    through :func:`fmt`, anything else as ``str``, a missing key as an empty cell."""
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    body = "".join(
        "| "
        + " | ".join(
            fmt(r.get(c)) if isinstance(r.get(c), float) else str(r.get(c, "")) for c in columns
        )
        + " |\n"
        for r in rows
    )
    return head + body
