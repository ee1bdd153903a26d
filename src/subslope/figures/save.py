"""The one figure saver and the footer every campaign figure carries.

Figures are drawn on a pyplot-free :class:`matplotlib.figure.Figure` (no global state,
any backend) and written atomically (:func:`subslope.io.atomic.atomic_write`), with the
run name both in the footer and in the file metadata (PDF Subject, PNG Description).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from subslope._version import __version__
from subslope.io.atomic import atomic_write

__all__ = ["footer", "save_figure"]


def footer(
    fig,
    run_name: str,
    source: str | None = None,
    extra: str | None = None,
    *,
    fontsize: float = 6.5,
    color: str = "0.35",
) -> None:
    """Draw ``config run_name=… · subslope <version> · source · extra`` along the bottom."""
    parts = [f"config run_name={run_name!r}", f"subslope {__version__}"]
    if source:
        parts.append(str(source))
    if extra:
        parts.append(extra)
    fig.text(
        0.5, 0.005, " · ".join(parts), ha="center", va="bottom", fontsize=fontsize, color=color
    )


def save_figure(
    fig,
    target: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
    *,
    run_name: str,
    dpi: int = 150,
    title: str | None = None,
) -> list[Path]:
    """Write ``fig`` atomically and return the paths written.

    ``target`` is either a stem (``results/figures/fig2`` → ``fig2.pdf`` and ``fig2.png``)
    or a sequence of output paths whose suffix gives each format. The title in the file
    metadata defaults to the figure's suptitle, else the file name.
    """
    if isinstance(target, (str, os.PathLike)):
        stem = Path(target)
        outputs = [stem.parent / f"{stem.name}.{fmt}" for fmt in ("pdf", "png")]
    else:
        outputs = [Path(p) for p in target]
    paths = []
    for out in outputs:
        fmt = out.suffix.lstrip(".")
        name = title or fig.get_suptitle() or out.stem
        key = "Subject" if fmt == "pdf" else "Description"
        meta = {"Title": name, key: f"run_name={run_name}"}
        with atomic_write(out) as tmp:
            fig.savefig(tmp, format=fmt, dpi=dpi, metadata=meta)
        paths.append(out)
    return paths
