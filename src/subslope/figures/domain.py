"""Figures of the domain check (:mod:`subslope.validation.domain`): the simulated
distribution of every statistic with the HST lenses marked, and the HST cutouts beside
simulated images on one common stretch."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd
from matplotlib.colors import AsinhNorm
from matplotlib.figure import Figure

from subslope.figures.save import footer

__all__ = ["LABELS", "domain_histograms", "domain_gallery", "source_cleaning"]

#: Axis label of each statistic.
LABELS = {
    "white_mean": "whitened mean in mask",
    "white_std": "whitened std in mask",
    "flux_centre": "flux within 0.3″ (e⁻/s)",
    "flux_annulus": "flux in 0.7–1.5 θ_E (e⁻/s)",
    "light_mag": "fitted lens-light mag",
    "light_r": "fitted R_sersic (″)",
    "light_n": "fitted n_sersic",
    "light_q": "fitted axis ratio q",
    "arc_snr": "peak arc S/N",
    "bright_fraction": "fraction of mask > 3σ",
    "border_level": "sky level at the border (e⁻/s)",
    "noise_lag1": "neighbouring pixels' noise correlation",
}


def domain_histograms(
    simulated: pd.DataFrame,
    real: pd.DataFrame,
    table: pd.DataFrame,
    statistics: Sequence[str],
    *,
    run_name: str,
    scene: str,
) -> Figure:
    """One panel per statistic: the simulated histogram, each HST lens a vertical line
    (red where the lens lies outside the 1–99% range of that statistic)."""
    n = len(statistics)
    ncols = 5
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(3.2 * ncols, 2.6 * nrows + 0.8))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_axis_off()
    for ax, stat in zip(axes.flat, statistics, strict=False):
        sim = simulated[stat].to_numpy(dtype=np.float64)
        sim = sim[np.isfinite(sim)]
        vals = real[stat].to_numpy(dtype=np.float64)
        lo, hi = np.nanpercentile(np.concatenate([sim, vals]), [0, 100]) if sim.size else (0, 1)
        ax.hist(sim, bins=40, range=(lo, hi), color="0.6", label=f"{scene} ({sim.size})")
        pct = table[f"{stat}_pct"].to_numpy()
        for v, p in zip(vals, pct, strict=True):
            bad = not (1.0 <= p <= 99.0)
            ax.axvline(v, color="crimson" if bad else "tab:blue", lw=1.0, alpha=0.8)
        out = int(np.sum(~((pct >= 1) & (pct <= 99))))
        ax.set_title(f"{LABELS.get(stat, stat)}: {out}/13 outside", fontsize=8)
        ax.tick_params(labelsize=7)
    inside = int(table["inside"].sum())
    fig.suptitle(
        f"Domain check: {inside} of {len(table)} HST lenses inside the simulated 1–99% "
        f"range of every statistic (grey: {scene} simulations; blue/red: HST lenses "
        "inside/outside)",
        fontsize=10,
    )
    footer(fig, run_name, "subslope.validation.domain")
    fig.tight_layout(rect=(0, 0.03, 1, 0.95))
    return fig


def domain_gallery(
    real_images: np.ndarray,
    names: Sequence[str],
    simulated_images: np.ndarray,
    *,
    run_name: str,
    scene: str,
    cmap: str = "magma",
) -> Figure:
    """The HST cutouts (top rows) and as many simulated images (bottom rows), all on one
    asinh stretch (limits: the 1st and 99.5th percentiles of all pixels shown)."""
    n = len(real_images)
    ncols = min(n, 7)
    rows_each = math.ceil(n / ncols)
    sims = np.asarray(simulated_images)[:n]
    allpix = np.concatenate([np.ravel(real_images), np.ravel(sims)])
    vmin, vmax = np.percentile(allpix, [1.0, 99.5])
    norm = AsinhNorm(linear_width=max(0.05 * (vmax - vmin), 1e-6), vmin=vmin, vmax=vmax)
    fig = Figure(figsize=(1.9 * ncols, 2.0 * 2 * rows_each + 0.8))
    axes = fig.subplots(2 * rows_each, ncols, squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for k in range(n):
        ax = axes[k // ncols, k % ncols]
        ax.imshow(real_images[k], origin="lower", cmap=cmap, norm=norm, interpolation="nearest")
        ax.set_title(names[k], fontsize=7)
    for k in range(len(sims)):
        ax = axes[rows_each + k // ncols, k % ncols]
        ax.imshow(sims[k], origin="lower", cmap=cmap, norm=norm, interpolation="nearest")
        ax.set_title(f"{scene} #{k}", fontsize=7)
    fig.suptitle(
        f"HST lenses (top) and {scene} simulations (bottom), one asinh stretch "
        f"[{vmin:.3g}, {vmax:.3g}] e⁻/s per pixel",
        fontsize=10,
    )
    footer(fig, run_name, "subslope.figures.domain")
    fig.tight_layout(rect=(0, 0.03, 1, 0.95))
    return fig


def source_cleaning(
    examples: Sequence[tuple[int, np.ndarray, np.ndarray, np.ndarray, float]],
    *,
    run_name: str,
    cmap: str = "magma",
) -> Figure:
    """COSMOS stamps before and after cleaning, one row per galaxy: the raw stamp, the
    footprint alone and the denoised stamp in its footprint, on one asinh stretch per row
    (in units of the stamp's noise σ, from −2 σ to the row's 99.5th percentile).
    ``examples``: ``(ident, raw, footprint only, denoised, σ)`` per galaxy."""
    n = len(examples)
    fig = Figure(figsize=(6.6, 2.1 * n + 0.8))
    axes = fig.subplots(n, 3, squeeze=False)
    titles = ("raw stamp", "footprint only", "denoised in footprint")
    for row, (ident, raw, foot, den, sigma) in zip(axes, examples, strict=True):
        panels = [np.asarray(a, dtype=np.float64) / sigma for a in (raw, foot, den)]
        vmax = float(np.percentile(panels[0], 99.5))
        norm = AsinhNorm(linear_width=2.0, vmin=-2.0, vmax=max(vmax, 3.0))
        for ax, img, title in zip(row, panels, titles, strict=True):
            ax.imshow(img, origin="lower", cmap=cmap, norm=norm, interpolation="nearest")
            ax.set_axis_off()
            ax.set_title(f"{ident}: {title}", fontsize=7)
    fig.suptitle(
        "COSMOS sources before and after cleaning (S/N per stamp pixel, asinh stretch)",
        fontsize=9,
    )
    footer(fig, run_name, "subslope.io.cosmos")
    fig.tight_layout(rect=(0, 0.03, 1, 0.96))
    return fig
