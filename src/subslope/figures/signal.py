"""The signal-budget figure: the ideal observer's Δχ² of each scene's subhalos per image,
with the smooth model fixed and refitted (:mod:`subslope.stages.signal_budget`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from subslope.figures.save import footer

__all__ = ["signal_budget_figure"]

#: Δχ² marks drawn on the figure: invisible, and an individual detection.
MARKS = ((1.0, "Δχ² = 1"), (25.0, "Δχ² = 25"))


def signal_budget_figure(
    labels: Sequence[str],
    fixed: Sequence[np.ndarray],
    refit: Sequence[np.ndarray],
    *,
    run_name: str = "",
    source: str | None = None,
) -> Figure:
    """One row per scene: the Δχ² of every image (dots) and its median (bar), with the
    smooth model fixed (grey) and after the linearised refit (black), on a log axis; the
    dashed lines mark Δχ² = 1 and 25. Images with Δχ² = 0 (no subhalos) sit at the
    left edge."""
    n = len(labels)
    fig = Figure(figsize=(7.5, 0.45 * n + 1.6))
    ax = fig.subplots()
    values = [v for arr in (*fixed, *refit) for v in np.asarray(arr, float) if v > 0]
    floor = 0.3 * min(values) if values else 0.1
    for row, (f, r) in enumerate(zip(fixed, refit)):
        y = n - 1 - row
        for arr, dy, color, name in ((f, 0.15, "0.6", "macro fixed"), (r, -0.15, "k", "refit")):
            arr = np.maximum(np.asarray(arr, dtype=float), floor)
            ax.scatter(arr, np.full(arr.size, y + dy), s=8, color=color, alpha=0.7,
                       label=name if row == 0 else None)  # fmt: skip
            if arr.size:
                ax.plot([np.median(arr)] * 2, [y + dy - 0.12, y + dy + 0.12], color=color, lw=2)
    for value, text in MARKS:
        ax.axvline(value, color="tab:red", ls="--", lw=0.8)
        ax.text(value, n - 0.45, text, color="tab:red", fontsize=7, ha="left")
    ax.set_xscale("log")
    ax.set_yticks(range(n))
    ax.set_yticklabels(list(reversed(list(labels))), fontsize=8)
    ax.set_ylim(-0.6, n - 0.2)
    ax.set_xlabel("Δχ² of the subhalos per image (inside the estimator's mask)")
    ax.legend(loc="lower right", fontsize=7)
    fig.suptitle("Signal budget: what an ideal observer could see of the subhalos", fontsize=10)
    footer(fig, run_name, source)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return fig
