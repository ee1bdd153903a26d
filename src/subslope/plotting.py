"""Figures of the workflow.

Every figure states, in its footer, the configuration (``run_name``) it came from.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure  # pyplot-free: works under any backend, no global state

from subslope import __version__
from subslope.observations import Observation

__all__ = ["log_stretch_limits", "plot_hst_gallery", "plot_scene_examples", "plot_scene_examples_from_shard"]


def log_stretch_limits(image: np.ndarray, floor_percentile: float = 1.0, dynamic_range: float = 1e3) -> tuple[float, float]:
    """Colour limits ``(vmin, vmax)`` of the logarithmic display of one image.

    ``vmax`` is the brightest pixel; ``vmin`` (the floor) is the ``floor_percentile``-th
    percentile of the pixel values, but never below ``vmax / dynamic_range``. Pixels
    below the floor, including zero or negative (sky-subtracted noise) pixels, are
    shown at the floor colour, so the stretch is defined for every image.
    """
    finite = image[np.isfinite(image)]
    vmax = float(finite.max()) if finite.size else 1.0
    if vmax <= 0:
        vmax = 1.0
    vmin = max(float(np.percentile(finite, floor_percentile)) if finite.size else 0.0, vmax / dynamic_range)
    return vmin, vmax


def plot_hst_gallery(
    observations: Sequence[Observation],
    outputs: Sequence[str | os.PathLike[str]],
    *,
    run_name: str,
    pixel_scale: float = 0.04,
    ncols: int = 5,
    cmap: str = "magma",
) -> None:
    """Gallery of the real HST cutouts, one panel per lens, titled with its SDSS name.

    Each panel is shown on its own logarithmic scale (limits from
    :func:`log_stretch_limits`); a 1″ bar is drawn on the first panel. The footer names
    the run. The figure is written to every path in ``outputs`` (format from the suffix).
    """
    if not observations:
        raise ValueError("plot_hst_gallery: no observations to plot")
    n = len(observations)
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(2.2 * ncols, 2.55 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for k, (ax, obs) in enumerate(zip(axes.flat, observations, strict=False)):
        vmin, vmax = log_stretch_limits(obs.image)
        ax.imshow(
            np.clip(obs.image, vmin, None),
            origin="lower",  # row index = y increasing upwards (docs/design.md)
            cmap=cmap,
            norm=LogNorm(vmin=vmin, vmax=vmax),
            interpolation="nearest",
        )
        ax.set_title(obs.name, fontsize=10)
        ax.text(
            0.03, 0.03, f"$z_l$={obs.z_lens:.3f}  $\\theta_E$={obs.theta_e:.2f}″",
            transform=ax.transAxes, color="white", fontsize=7, ha="left", va="bottom",
        )
        if k == 0:
            npix = obs.image.shape[1]
            bar = 1.0 / pixel_scale
            x0 = npix - 0.08 * npix - bar
            y0 = npix - 0.1 * npix
            ax.plot([x0, x0 + bar], [y0, y0], color="white", lw=2)
            ax.text(x0 + bar / 2, y0 - 2, '1″', color="white", fontsize=8, ha="center", va="top")
    fig.suptitle(f"HST ACS F814W cutouts of the {n} lenses (log scale, e$^-$/s per pixel)", fontsize=11)
    fig.text(
        0.5, 0.005,
        f"config run_name={run_name!r} · subslope {__version__} · "
        f"{pixel_scale}″/pixel · colour range per panel: 1st percentile (≥ max/1000) to max",
        ha="center", va="bottom", fontsize=7, color="0.3",
    )
    fig.tight_layout(rect=(0, 0.025, 1, 0.97), h_pad=1.2)
    for out in outputs:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        # The run name also goes into the file's metadata, so it is machine-readable.
        fig.savefig(out, dpi=150, metadata={"Title": f"subslope HST gallery, run_name={run_name}"})


def plot_scene_examples(
    images: np.ndarray,
    masks: np.ndarray,
    titles: Sequence[str],
    outputs: Sequence[str | os.PathLike[str]],
    *,
    scene: str,
    run_name: str,
    threshold_fraction: float,
    ncols: int = 4,
    cmap: str = "magma",
) -> None:
    """Grid of simulated images (log scale), each with the contour of its arc mask.

    ``images`` (k, H, W) e⁻/s per pixel; ``masks`` (k, H, W) booleans (pixels of the
    smooth model above ``threshold_fraction`` of its maximum: where arc-placed subhalos
    may sit); ``titles`` one per panel. Written to every path of ``outputs``.
    """
    images = np.asarray(images)
    if images.ndim != 3 or len(images) == 0 or len(masks) != len(images) or len(titles) != len(images):
        raise ValueError("plot_scene_examples: images (k, H, W), masks and titles must have the same k >= 1")
    n = len(images)
    ncols = min(ncols, n)
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(2.4 * ncols, 2.6 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for ax, img, mask, title in zip(axes.flat, images, masks, titles, strict=False):
        vmin, vmax = log_stretch_limits(img)
        ax.imshow(np.clip(img, vmin, None), origin="lower", cmap=cmap, norm=LogNorm(vmin=vmin, vmax=vmax),
                  interpolation="nearest")
        if np.any(mask) and not np.all(mask):
            ax.contour(np.asarray(mask, dtype=float), levels=[0.5], colors="cyan", linewidths=0.7, origin="lower")
        ax.set_title(title, fontsize=8)
    fig.suptitle(f"Simulated images of scene {scene!r} (log scale, e$^-$/s per pixel); cyan: smooth model "
                 f"> {threshold_fraction:g} × max", fontsize=10)
    fig.text(0.5, 0.005, f"config run_name={run_name!r} · subslope {__version__}", ha="center", va="bottom",
             fontsize=7, color="0.3")
    fig.tight_layout(rect=(0, 0.025, 1, 0.96), h_pad=1.0)
    for out in outputs:
        out = Path(out)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=130, metadata={"Title": f"subslope scene examples {scene}, run_name={run_name}"})


def plot_scene_examples_from_shard(
    shard_path: str | os.PathLike[str],
    outputs: Sequence[str | os.PathLike[str]],
    *,
    run_name: str,
    n: int = 8,
    cosmos: str | os.PathLike[str] | None = None,
) -> list[int]:
    """Scene-example figure of the first ``n`` images of a shard; returns their indices.

    The arc masks are recomputed from the stored parameters with
    :func:`subslope.simulate.smooth_models` (nothing is re-sampled). Titles give the
    label γ (or the concentration multiplier a of CDM scenes), N_sub and N_LoS.
    """
    from subslope.shards import open_shard
    from subslope.simulate import smooth_models

    with open_shard(shard_path) as shard:
        k = min(int(n), len(shard))
        idx = list(range(k))
        images = shard.images[:k]
        p = shard.params
        scene = shard.attrs["scene"]
        frac = float(shard.attrs["scene_spec"]["subhalos"]["threshold_fraction"])
        n_los = shard.los["counts"]
        titles = []
        for i in idx:
            label = f"γ={p['gamma_sub'][i]:.2f}" if "gamma_sub" in p else f"a={p['c_multiplier'][i]:g}"
            n_sub = int(p["n_sub"][i]) if "n_sub" in p else 0
            titles.append(f"{label}  N_sub={n_sub}  N_LoS={int(n_los[i])}")
    smooth = smooth_models(shard_path, idx, cosmos=cosmos)
    peak = smooth.reshape(k, -1).max(axis=1)
    masks = smooth > frac * peak[:, None, None]
    plot_scene_examples(images, masks, titles, outputs, scene=scene, run_name=run_name, threshold_fraction=frac)
    return idx
