"""Does the simulation look like the data? Summary statistics of lens images, computed the
same way on simulated images and on the real HST cutouts, and where each real lens falls
in the simulated distribution (``docs/simulation.md``, "Domain check").

Per image (:data:`STATISTICS`):

- ``theta_e``: the Einstein radius (simulated, or the catalogue's): a lens outside the
  training prior's range sits at the edge of the simulated distribution;
- ``white_mean``, ``white_std``: mean and std of the whitened image (training whitening)
  over the estimator's mask (``mask_factor`` θ_E about the lens centre);
- ``flux_centre``: flux within 0.3″ of the lens centre (e⁻/s);
- ``flux_annulus``: flux in the annulus 0.7–1.5 θ_E (e⁻/s);
- ``light_mag``, ``light_r``, ``light_n``, ``light_q``: the PSF-convolved Sérsic fit of
  the lens light with the arcs masked (:func:`subslope.physics.light.fit.fit_lens_light`);
- ``arc_snr``: the peak of (image − fitted lens light) / σ over the annulus, σ² = σ_bg² +
  max(model, 0)/t the detector noise of the fitted light, with compact objects
  (:func:`compact_objects`: companions, stars, cosmic-ray residue) masked first;
- ``bright_fraction``: the fraction of the mask's pixels above 3 σ_bg;
- ``border_level``: the sky level, the sigma-clipped median of the image's outer
  ``BORDER`` pixels (:func:`border_level`);
- ``noise_lag1``: the correlation of neighbouring pixels' noise (:func:`noise_lag1`) in
  the S/N residual of the lens-light fit beyond the arcs' annulus (r > 1.5 θ_E), compact
  objects masked: 0 for independent pixels; drizzled HST images correlate their
  neighbours.

The lens centre is measured on every image with
:func:`subslope.io.observations.find_lens_centre` (as for the HST lenses in the analysis);
θ_E is the simulated one or the catalogue's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from subslope.io.observations import find_lens_centre
from subslope.nre.inputs import InputTransform
from subslope.nre.preprocess import preprocess
from subslope.physics.grid import pixel_grid
from subslope.physics.light.fit import fit_lens_light
from subslope.physics.light.subtract import fit_input_light, model_images

__all__ = [
    "STATISTICS",
    "image_statistics",
    "domain_percentiles",
    "spread_table",
    "border_level",
    "noise_lag1",
    "compact_objects",
    "CENTRE_RADIUS",
    "ANNULUS",
    "BORDER",
]

STATISTICS = (
    "theta_e",
    "white_mean",
    "white_std",
    "flux_centre",
    "flux_annulus",
    "light_mag",
    "light_r",
    "light_n",
    "light_q",
    "arc_snr",
    "bright_fraction",
    "border_level",
    "noise_lag1",
)
#: Radius of the central aperture, arcsec.
CENTRE_RADIUS = 0.3
#: Annulus of the arcs, in units of θ_E.
ANNULUS = (0.7, 1.5)
#: Width of the image frame of :func:`border_level`, pixels.
BORDER = 5
#: A compact object (:func:`compact_objects`): a connected region of at most this many
#: pixels above this S/N, masked with a margin of this many pixels.
COMPACT_SNR, COMPACT_MAX_PIXELS, COMPACT_MARGIN = 5.0, 16, 2


def border_level(images, width: int = BORDER) -> np.ndarray:
    """Sky level of each image ``(B, H, W)``: the 3σ-clipped median of its outer
    ``width`` pixels on every side (astropy ``sigma_clipped_stats``), e⁻/s per pixel."""
    from astropy.stats import sigma_clipped_stats

    images = np.asarray(images, dtype=np.float64)
    frame = np.ones(images.shape[1:], dtype=bool)
    frame[width:-width, width:-width] = False
    return np.array([sigma_clipped_stats(im[frame], sigma=3.0)[1] for im in images])


#: Pixels of :func:`noise_lag1` whose high-passed |S/N| exceeds this are left out
#: (sources, not noise); the side of its running median, pixels.
NOISE_CLIP, NOISE_HIGHPASS = 4.0, 5


def noise_lag1(snr, region, *, size: int = NOISE_HIGHPASS) -> np.ndarray:
    """Lag-1 noise correlation of S/N residual maps ``snr`` ``(B, H, W)`` over ``region``
    (bool, same shape).

    Each map is high-passed first (minus its ``size`` × ``size`` running median), so that
    what a Sérsic fit leaves of a real galaxy, smooth over several pixels, does not count
    as correlated noise. Then the Pearson correlation of the pairs of horizontally and
    vertically adjacent pixels that are both in the region and both within
    ``|value| <=`` :data:`NOISE_CLIP`. Independent pixels give −0.04 (the high-pass
    anticorrelates neighbours slightly); the 3-tap kernel of
    :func:`subslope.physics.instrument.correlate_noise` with lag-1 correlation ρ gives
    0.15, 0.19, 0.23, 0.27, 0.31 at ρ = 0.25, 0.30, 0.35, 0.40, 0.45 (noise alone). NaN
    for an image with no such pairs.
    """
    from scipy.ndimage import median_filter

    snr = np.asarray(snr, dtype=np.float64)
    high = snr - median_filter(snr, size=(1, size, size), mode="reflect")
    keep = np.asarray(region, dtype=bool) & (np.abs(high) <= NOISE_CLIP)
    out = np.full(snr.shape[0], np.nan)
    for k, (s, m) in enumerate(zip(high, keep, strict=True)):
        if not m.any():
            continue
        d = np.where(m, s - s[m].mean(), 0.0)
        pairs = [(d[:, 1:], d[:, :-1], m[:, 1:] & m[:, :-1]), (d[1:], d[:-1], m[1:] & m[:-1])]
        a = np.concatenate([x[p] for x, _, p in pairs])
        b = np.concatenate([y[p] for _, y, p in pairs])
        if a.size:
            out[k] = float(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return out


def compact_objects(snr) -> np.ndarray:
    """Mask ``(B, H, W)`` of the compact objects of S/N maps ``snr``: 8-connected regions
    above :data:`COMPACT_SNR` with at most :data:`COMPACT_MAX_PIXELS` pixels, dilated by
    :data:`COMPACT_MARGIN`. A lensed arc is larger and stays unmasked; a companion
    galaxy's core, a star or a cosmic-ray residue is masked. The same rule runs on
    simulated and real images."""
    from scipy import ndimage

    snr = np.asarray(snr, dtype=np.float64)
    out = np.zeros(snr.shape, dtype=bool)
    eight = np.ones((3, 3), dtype=bool)
    for k, m in enumerate(snr):
        labels, n = ndimage.label(m > COMPACT_SNR, structure=eight)
        if n == 0:
            continue
        sizes = np.bincount(labels.ravel())
        small = np.flatnonzero(sizes <= COMPACT_MAX_PIXELS)
        small = small[small > 0]
        if small.size:
            out[k] = ndimage.binary_dilation(
                np.isin(labels, small), structure=eight, iterations=COMPACT_MARGIN
            )
    return out


def image_statistics(
    images,
    theta_e,
    *,
    psf,
    background_sigma: float,
    exposure_time: float,
    whitening: tuple[float, float],
    pixel_scale: float,
    mask_factor: float = 1.5,
    lens_centre: Mapping[str, Any] | None = None,
    chunk: int = 100,
    inputs: InputTransform | None = None,
) -> pd.DataFrame:
    """The statistics of :data:`STATISTICS` for ``images`` ``(B, H, W)`` (e⁻/s per pixel)
    with Einstein radii ``theta_e`` ``(B,)`` (arcsec); one row per image, plus the
    measured lens centre ``lens_x``, ``lens_y`` (arcsec). ``white_*`` are taken of what
    the estimator sees: the images after the input transform ``inputs``
    (:mod:`subslope.nre.inputs`; a lens-light-subtracting one fits each image as the
    shard jobs do) and the whitening."""
    images = np.asarray(images, dtype=np.float64)
    theta_e = np.asarray(theta_e, dtype=np.float64).reshape(-1)
    if images.ndim != 3 or images.shape[0] != theta_e.size:
        raise ValueError(
            f"images {images.shape} and theta_e {theta_e.shape} do not describe the same images"
        )
    rows = []
    for s in range(0, len(images), chunk):
        rows.append(
            _chunk_statistics(
                images[s : s + chunk],
                theta_e[s : s + chunk],
                psf,
                background_sigma,
                exposure_time,
                whitening,
                pixel_scale,
                mask_factor,
                dict(lens_centre or {}),
                inputs or InputTransform(),
            )
        )
    return pd.concat(rows, ignore_index=True)


def _chunk_statistics(
    images, theta_e, psf, sigma_bg, t_exp, whitening, pix, mask_factor, lc, inputs
):
    n, h, _ = images.shape
    centres = np.array([find_lens_centre(im, pixel_scale=pix, **lc) for im in images])
    fit = fit_lens_light(
        images,
        psf,
        centres,
        theta_e,
        background_sigma=sigma_bg,
        exposure_time=t_exp,
        pixel_scale=pix,
    )
    xs, ys = (a.numpy() for a in pixel_grid(h, pix))
    r = np.hypot(xs[None] - centres[:, 0, None, None], ys[None] - centres[:, 1, None, None])
    te = theta_e[:, None, None]
    annulus = (r > ANNULUS[0] * te) & (r < ANNULUS[1] * te)
    inside = r <= mask_factor * te
    light = None
    if inputs.needs_light:
        kw = {"background_sigma": sigma_bg, "exposure_time": t_exp, "pixel_scale": pix}
        fitted = fit_input_light(images, centres, theta_e, psf, **kw)
        light = model_images(fitted, psf, h, pix)
    white = preprocess(
        inputs.apply(images, light),
        theta_e,
        centres[:, 0],
        centres[:, 1],
        *whitening,
        pixel_scale=pix,
        mask_factor=None,
    )
    sigma = np.sqrt(sigma_bg**2 + np.clip(fit.model, 0, None) / t_exp)
    snr = (images - fit.model) / sigma
    compact = compact_objects(snr)
    arcs = annulus & ~compact
    outside = (r > ANNULUS[1] * te) & ~compact

    def over(mask, values, op):
        return np.array([op(values[k][mask[k]]) if mask[k].any() else np.nan for k in range(n)])

    return pd.DataFrame(
        {
            "lens_x": centres[:, 0],
            "lens_y": centres[:, 1],
            "theta_e": theta_e,
            "white_mean": over(inside, white, np.mean),
            "white_std": over(inside, white, np.std),
            "flux_centre": (images * (r <= CENTRE_RADIUS)).sum((1, 2)),
            "flux_annulus": (images * annulus).sum((1, 2)),
            "light_mag": fit.mag,
            "light_r": fit.r_sersic,
            "light_n": fit.n_sersic,
            "light_q": fit.q,
            "arc_snr": over(arcs, snr, np.max),
            "bright_fraction": over(inside, images > 3.0 * sigma_bg, np.mean),
            "border_level": border_level(images),
            "noise_lag1": noise_lag1(snr, outside),
        }
    )


def domain_percentiles(
    simulated: pd.DataFrame,
    real: pd.DataFrame,
    names: Sequence[str],
    *,
    bounds: tuple[float, float] = (1.0, 99.0),
    statistics: Sequence[str] = STATISTICS,
) -> pd.DataFrame:
    """Percentile of each real image's statistic in the simulated distribution (the
    percentage of simulated values below it, ties counted half), one row per system;
    ``inside`` when every percentile lies within ``bounds``, and ``outside`` lists the
    statistics that do not."""
    out = {"system": list(names)}
    ok = np.ones(len(real), dtype=bool)
    bad: list[list[str]] = [[] for _ in range(len(real))]
    for stat in statistics:
        sim = np.sort(simulated[stat].to_numpy(dtype=np.float64))
        sim = sim[np.isfinite(sim)]
        val = real[stat].to_numpy(dtype=np.float64)
        below = np.searchsorted(sim, val, side="left")
        equal = np.searchsorted(sim, val, side="right") - below
        pct = 100.0 * (below + 0.5 * equal) / max(sim.size, 1)
        pct = np.where(np.isfinite(val) & (sim.size > 0), pct, np.nan)
        out[f"{stat}_pct"] = pct
        within = (pct >= bounds[0]) & (pct <= bounds[1])
        ok &= within
        for k in np.flatnonzero(~within):
            bad[k].append(stat)
    table = pd.DataFrame(out)
    table["inside"] = ok
    table["outside"] = [";".join(b) for b in bad]
    return table


def spread_table(
    simulated: pd.DataFrame,
    real: pd.DataFrame,
    *,
    bounds: tuple[float, float] = (1.0, 99.0),
    statistics: Sequence[str] = STATISTICS,
) -> pd.DataFrame:
    """Per statistic: the simulated ``bounds`` percentiles (``sim_lo``, ``sim_hi``), the
    real range (``hst_min``, ``hst_max``) and ``width_ratio``, the simulated width over
    the real one: how much wider than the data the simulation is."""
    rows = []
    for stat in statistics:
        sim = simulated[stat].to_numpy(dtype=np.float64)
        sim = sim[np.isfinite(sim)]
        val = real[stat].to_numpy(dtype=np.float64)
        val = val[np.isfinite(val)]
        lo, hi = np.percentile(sim, bounds) if sim.size else (np.nan, np.nan)
        width = val.max() - val.min() if val.size else np.nan
        rows.append(
            {
                "statistic": stat,
                "sim_lo": lo,
                "sim_hi": hi,
                "hst_min": val.min() if val.size else np.nan,
                "hst_max": val.max() if val.size else np.nan,
                "width_ratio": (hi - lo) / width if width and width > 0 else np.nan,
            }
        )
    return pd.DataFrame(rows)
