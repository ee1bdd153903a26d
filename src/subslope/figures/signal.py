"""The signal-budget figure: the ideal observer's Δχ² of each scene's subhalos per image,
with the smooth model fixed and refitted (:mod:`subslope.stages.signal_budget`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from subslope.figures.save import footer

__all__ = ["response_figure", "signal_budget_figure"]

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
    smooth model fixed (grey) and after the full refit (black), on a log axis; the
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


def response_figure(table, *, run_name: str = "", source: str | None = None) -> Figure:
    """The estimator's response (shift of the stack γ_MLE when the halos are removed)
    against the stack's ideal-observer Δχ² after the refit, one point per scene and
    multiplier (NFW, tNFW, EPL), error bars where the shift is paired."""
    fig = Figure(figsize=(6.0, 4.2))
    ax = fig.subplots()
    if not len(table):
        ax.text(0.5, 0.5, "no signal budget or null tests in this campaign", ha="center",
                transform=ax.transAxes)  # fmt: skip
        footer(fig, run_name, source)
        return fig
    styles = {"nfw": ("tab:blue", "o"), "tnfw": ("tab:orange", "s"), "test_epl": ("k", "D")}
    for scene, group in table.groupby("scene", sort=False):
        color, marker = styles.get(scene, ("tab:gray", "^"))
        x = np.maximum(group["stack_refit"].to_numpy(float), 1e-3)
        ax.errorbar(
            x, group["shift"], yerr=group["shift_se"].fillna(0.0), fmt=marker, color=color,
            label=scene + ("" if group["paired"].all() else " (medians, not paired)"),
        )  # fmt: skip
        for xi, yi, a in zip(x, group["shift"], group["multiplier"]):
            if np.isfinite(a):
                ax.annotate(f"a={a:g}", (xi, yi), textcoords="offset points", xytext=(4, 4),
                            fontsize=7, color=color)  # fmt: skip
    ax.axhline(0.0, color="0.5", lw=0.8)
    for value, _ in MARKS:
        ax.axvline(value, color="tab:red", ls="--", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("ideal observer's Δχ² of a stack, smooth model refitted")
    ax.set_ylabel("shift of the stack γ_MLE (with − without halos)")
    ax.legend(fontsize=7)
    fig.suptitle("Estimator response against the signal the images hold", fontsize=10)
    footer(fig, run_name, source)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return fig
