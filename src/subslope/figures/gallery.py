"""Figures of the workflow.

Every figure states, in its footer, the configuration (``run_name``) it came from.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure  # pyplot-free: works under any backend, no global state
from matplotlib.patches import Rectangle

from subslope.figures.save import footer, save_figure
from subslope.io.observations import Observation
from subslope.physics.instrument import PIXEL_SCALE

__all__ = [
    "log_stretch_limits",
    "plot_hst_gallery",
    "plot_scene_examples",
    "plot_scene_examples_from_shard",
    "stiff_case_panels",
    "stiff_cases_figure",
]


def log_stretch_limits(
    image: np.ndarray, floor_percentile: float = 1.0, dynamic_range: float = 1e3
) -> tuple[float, float]:
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
    vmin = max(
        float(np.percentile(finite, floor_percentile)) if finite.size else 0.0, vmax / dynamic_range
    )
    return vmin, vmax


def plot_hst_gallery(
    observations: Sequence[Observation],
    outputs: Sequence[str | os.PathLike[str]],
    *,
    run_name: str,
    pixel_scale: float = PIXEL_SCALE,
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
            0.03,
            0.03,
            f"$z_l$={obs.z_lens:.3f}  $\\theta_E$={obs.theta_e:.2f}″",
            transform=ax.transAxes,
            color="white",
            fontsize=7,
            ha="left",
            va="bottom",
        )
        if k == 0:
            npix = obs.image.shape[1]
            bar = 1.0 / pixel_scale
            x0 = npix - 0.08 * npix - bar
            y0 = npix - 0.1 * npix
            ax.plot([x0, x0 + bar], [y0, y0], color="white", lw=2)
            ax.text(x0 + bar / 2, y0 - 2, "1″", color="white", fontsize=8, ha="center", va="top")
    fig.suptitle(
        f"HST ACS F814W cutouts of the {n} lenses (log scale, e$^-$/s per pixel)", fontsize=11
    )
    footer(
        fig,
        run_name,
        f"{pixel_scale}″/pixel · colour range per panel: 1st percentile (≥ max/1000) to max",
        fontsize=7,
        color="0.3",
    )
    fig.tight_layout(rect=(0, 0.025, 1, 0.97), h_pad=1.2)
    save_figure(fig, list(outputs), run_name=run_name, dpi=150, title="subslope HST gallery")


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
    extra_panels: Sequence[tuple[np.ndarray, np.ndarray, str]] | None = None,
) -> None:
    """Grid of simulated images (log scale), each with the contour of its arc mask.

    ``images`` (k, H, W) e⁻/s per pixel; ``masks`` (k, H, W) booleans (pixels of the
    smooth model above ``threshold_fraction`` of its maximum: where arc-placed subhalos
    may sit); ``titles`` one per panel. ``extra_panels``: further (image, mask, title)
    panels appended after them (e.g. :func:`stiff_case_panels`). Written to every path
    of ``outputs``.
    """
    if extra_panels:
        images = list(np.asarray(images)) + [np.asarray(p[0]) for p in extra_panels]
        masks = list(np.asarray(masks)) + [np.asarray(p[1]) for p in extra_panels]
        titles = list(titles) + [p[2] for p in extra_panels]
    images = np.asarray(images)
    if (
        images.ndim != 3
        or len(images) == 0
        or len(masks) != len(images)
        or len(titles) != len(images)
    ):
        raise ValueError(
            "plot_scene_examples: images (k, H, W), masks and titles must have the same k >= 1"
        )
    n = len(images)
    ncols = min(ncols, n)
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(2.4 * ncols, 2.6 * nrows + 0.6))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    for ax, img, mask, title in zip(axes.flat, images, masks, titles, strict=False):
        vmin, vmax = log_stretch_limits(img)
        ax.imshow(
            np.clip(img, vmin, None),
            origin="lower",
            cmap=cmap,
            norm=LogNorm(vmin=vmin, vmax=vmax),
            interpolation="nearest",
        )
        if np.any(mask) and not np.all(mask):
            ax.contour(
                np.asarray(mask, dtype=float),
                levels=[0.5],
                colors="cyan",
                linewidths=0.7,
                origin="lower",
            )
        ax.set_title(title, fontsize=8)
    fig.suptitle(
        f"Simulated images of scene {scene!r} (log scale, e$^-$/s per pixel); cyan: smooth model "
        f"> {threshold_fraction:g} × max",
        fontsize=10,
    )
    footer(fig, run_name, fontsize=7, color="0.3")
    fig.tight_layout(rect=(0, 0.025, 1, 0.96), h_pad=1.0)
    save_figure(
        fig, list(outputs), run_name=run_name, dpi=130, title=f"subslope scene examples {scene}"
    )


def plot_scene_examples_from_shard(
    shard_path: str | os.PathLike[str],
    outputs: Sequence[str | os.PathLike[str]],
    *,
    run_name: str,
    n: int = 8,
    cosmos: str | os.PathLike[str] | None = None,
    stiff_cases: bool = False,
) -> list[int]:
    """Scene-example figure of the first ``n`` images of a shard; returns their indices.

    The arc masks are recomputed from the stored parameters with
    :func:`subslope.simulation.rerender.smooth_models` (nothing is re-sampled). Titles give the
    label γ (or the concentration multiplier a of CDM scenes), N_sub and N_LoS. With
    ``stiff_cases=True`` two panels of docs/simulation.md's stiff cases are appended
    (:func:`stiff_case_panels` with the shard's PSF: N_sub = 1500 at γ = 2.5 and 1.2).
    """
    from subslope.io.shards import open_shard
    from subslope.simulation.rerender import smooth_models

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
            label = (
                f"γ={p['gamma_sub'][i]:.2f}" if "gamma_sub" in p else f"a={p['c_multiplier'][i]:g}"
            )
            n_sub = int(p["n_sub"][i]) if "n_sub" in p else 0
            titles.append(f"{label}  N_sub={n_sub}  N_LoS={int(n_los[i])}")
    smooth = smooth_models(shard_path, idx, cosmos=cosmos)
    peak = smooth.reshape(k, -1).max(axis=1)
    masks = smooth > frac * peak[:, None, None]
    extra = None
    if stiff_cases:
        with open_shard(shard_path) as shard:
            psf = np.asarray(shard.psf)
        extra = stiff_case_panels(psf)
    plot_scene_examples(
        images,
        masks,
        titles,
        outputs,
        scene=scene,
        run_name=run_name,
        threshold_fraction=frac,
        extra_panels=extra,
    )
    return idx


def stiff_case_panels(
    psf, *, seed: int = 6, n_sub: int = 1500, gammas=(2.5, 1.2), result: dict | None = None
) -> list[tuple[np.ndarray, np.ndarray, str]]:
    """(image, arc mask, title) panels of the stiff cases (sheet on, as simulated) for
    :func:`plot_scene_examples`'s ``extra_panels``; ``result`` reuses a
    :func:`subslope.validation.stiff.stiff_cases` output instead of rendering."""
    from subslope.validation import stiff as diagnostics

    res = result or diagnostics.stiff_cases(
        psf, seed=seed, n_sub=n_sub, gammas=gammas, sheets=(True,)
    )
    out = []
    for case in res["cases"]:
        if case.gamma is not None and case.sheet and case.gamma in gammas:
            out.append(
                (
                    res["images"][case.label],
                    res["arc_mask"],
                    f"stiff: γ={case.gamma:g} N_sub={case.n_sub} (arc {case.arc_ratio:.2f}×)",
                )
            )
    return out


def stiff_cases_figure(
    result: dict, outputs: Sequence[str | os.PathLike[str]], *, run_name: str, cmap: str = "magma"
) -> None:
    """Figure of :func:`subslope.validation.stiff.stiff_cases`: the smooth reference and every
    (γ, sheet) case on one common log scale, arc mask in cyan, numbers in the titles."""
    cases = result["cases"]
    n = len(cases)
    ncols = min(n, 5)
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(2.9 * ncols, 3.1 * nrows + 0.7))
    axes = fig.subplots(nrows, ncols, squeeze=False)
    for ax in axes.flat:
        ax.set_axis_off()
    vmax = max(float(np.max(result["images"][c.label])) for c in cases)
    vmin = vmax / 1e3
    rows, cols = result["centre"]
    for ax, c in zip(axes.flat, cases, strict=False):
        img = result["images"][c.label]
        ax.imshow(
            np.clip(img, vmin, None),
            origin="lower",
            cmap=cmap,
            norm=LogNorm(vmin=vmin, vmax=vmax),
            interpolation="nearest",
        )
        ax.contour(
            np.asarray(result["arc_mask"], dtype=float),
            levels=[0.5],
            colors="cyan",
            linewidths=0.6,
            origin="lower",
        )
        ax.add_patch(
            Rectangle((cols.start - 0.5, rows.start - 0.5), 5, 5, fill=False, ec="lime", lw=0.6)
        )
        extra = (
            ""
            if c.gamma is None
            else f"\nmean Σκ_sub={c.kappa_mean:.2f} [{c.kappa_min:.2f}, {c.kappa_max:.3g}]"
        )
        ax.set_title(
            f"{c.label}\narc {c.arc_ratio:.2f}× · total {c.total_ratio:.2f}× · "
            f"centre {c.centre_flux:.3f} e⁻/s{extra}",
            fontsize=7,
        )
    fig.suptitle(
        "docs/simulation.md stiff cases: EPL subhalos on the arc (no lens light, no noise; "
        "common log scale, "
        "e$^-$/s per pixel); cyan: smooth arc mask, green: central 5×5",
        fontsize=9,
    )
    footer(
        fig,
        run_name,
        "'sheet off' is a diagnostic only (the simulator always includes the negative sheet)",
        fontsize=7,
        color="0.3",
    )
    fig.tight_layout(rect=(0, 0.025, 1, 0.95), h_pad=1.0)
    save_figure(fig, list(outputs), run_name=run_name, dpi=130, title="subslope stiff cases")
