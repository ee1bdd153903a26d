"""Training curves: loss per epoch and learning rate, from ``training_log.csv``."""

from __future__ import annotations

import math
from pathlib import Path

from subslope.figures.save import footer, save_figure

__all__ = ["plot_training_curves"]


def plot_training_curves(log_csv, stem, *, run_name: str, source: str | None = None) -> list[Path]:
    """Training and validation loss (and learning rate) per epoch, from ``training_log.csv``."""
    import pandas as pd
    from matplotlib.figure import Figure

    frame = pd.read_csv(log_csv)
    fig = Figure(figsize=(5.6, 4.2))
    ax = fig.subplots()
    ax.plot(frame["epoch"], frame["train_loss"], "o-", label="training loss", color="#444444")
    ax.plot(frame["epoch"], frame["val_loss"], "s-", label="validation loss", color="#c2185b")
    ax.axhline(math.log(2), color="0.6", ls=":", lw=1, label="chance (ln 2)")
    best = int(frame["val_loss"].idxmin())
    ax.plot(
        frame["epoch"][best],
        frame["val_loss"][best],
        "*",
        ms=12,
        color="#c2185b",
        label="best (kept)",
    )
    ax.set_xlabel("epoch")
    ax.set_ylabel("NRE loss (binary cross-entropy)")
    if "lr" in frame:
        ax2 = ax.twinx()
        ax2.plot(frame["epoch"], frame["lr"], color="0.5", lw=0.8, ls="--")
        ax2.set_yscale("log")
        ax2.set_ylabel("learning rate (dashed)", color="0.4")
    ax.legend(fontsize=8, frameon=False)
    ax.grid(alpha=0.25)
    fig.suptitle("Estimator training curves", fontsize=10)
    footer(fig, run_name, source)
    fig.subplots_adjust(bottom=0.16, top=0.9, right=0.86)
    return save_figure(fig, stem, run_name=run_name)
