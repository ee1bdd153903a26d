r"""Effective density slope of (t)NFW subhalos: the power-law slope the images see.

A subhalo with 3-D density :math:`\rho\propto r^{-\gamma}` has a radial deflection
:math:`\alpha(R)\propto R^{2-\gamma}`, so its slope is :math:`\gamma = 2 - d\ln\alpha/d\ln R`
at every radius. An NFW or truncated-NFW subhalo has no single slope: its logarithmic
slope runs from 1 (inside R_s) to 3 (NFW, outside R_s) or 4 (tNFW, beyond r_t). The
images resolve a subhalo's deflection only over a band of projected radii, from about
one pixel (below it the PSF blurs the perturbation away) to a few tenths of an arcsec
(beyond it the perturbation is a smooth change that the macro model absorbs). The
*effective slope* of a subhalo is the least-squares slope of ln α against ln R over that
band, written as a density slope,

.. math::

    \gamma_\mathrm{eff} = 2 - \frac{\sum_k (u_k - \bar u)(v_k - \bar v)}{\sum_k (u_k - \bar u)^2},
    \qquad u_k = \ln R_k,\; v_k = \ln\alpha(R_k),

over radii R_k spaced evenly in ln R on [r_min, r_max] (exact for a power law). It
follows the spirit of Şengül & Dvorkin (2022, "Probing dark matter with strong
gravitational lensing through an effective density slope"), who characterise a
perturber by the slope of its deflection where the data constrain it; the band here is
the project's choice, stated with the numbers it gives (docs/physics.md).

A population's effective slope weights each subhalo by the signal it puts into an image:
the squared deflection averaged over the band, :math:`w = \langle\alpha^2\rangle_k`
(the ideal observer's Δχ² of a small deflection grows with its square). The weighting
ignores where the subhalo sits relative to the arcs; it is the slope a population would
show if every subhalo were equally well placed.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from subslope.physics.profiles.nfw import NFW_G1, nfw_g_over_x2
from subslope.physics.profiles.tnfw import tnfw_g_over_x2

__all__ = [
    "RESOLVED_RADII",
    "band_radii",
    "log_slope",
    "radial_deflection",
    "effective_slopes",
    "population_slope",
]

#: Band of projected radii (arcsec) over which the images resolve a subhalo's deflection:
#: one 0.04" pixel to ten pixels.
RESOLVED_RADII = (0.04, 0.4)


def band_radii(r_min: float = RESOLVED_RADII[0], r_max: float = RESOLVED_RADII[1], n: int = 16):
    """``n`` radii (arcsec, float64) evenly spaced in ln R on ``[r_min, r_max]``."""
    if not (0 < r_min < r_max and math.isfinite(r_max)):
        raise ValueError(f"need 0 < r_min < r_max < inf, got r_min={r_min!r}, r_max={r_max!r}")
    if int(n) < 2:
        raise ValueError(f"need at least 2 radii, got n={n!r}")
    return np.exp(np.linspace(math.log(r_min), math.log(r_max), int(n)))


def log_slope(radii, values) -> np.ndarray:
    """Least-squares slope of ln ``values`` against ln ``radii`` along the last axis.

    ``radii``: (K,) positive; ``values``: (..., K) positive. Returns (...,).
    """
    u = np.log(np.asarray(radii, dtype=np.float64))
    v = np.log(np.asarray(values, dtype=np.float64))
    du = u - u.mean()
    return ((v - v.mean(axis=-1, keepdims=True)) * du).sum(axis=-1) / (du * du).sum()


def radial_deflection(profile: str, radii, r_s, alpha_rs, r_t=None) -> np.ndarray:
    """|α|(R) in arcsec, shape (N, K), of N spherical (t)NFW halos at the K ``radii``.

    ``profile``: ``"nfw"`` or ``"tnfw"``; ``r_s``, ``alpha_rs``, ``r_t`` (tNFW): (N,)
    arcsec, as :func:`subslope.simulation.subhalos.nfw_lens_parameters` gives them.
    Evaluated in float64 with the renderer's profile functions
    (:mod:`subslope.physics.profiles.nfw`, :mod:`subslope.physics.profiles.tnfw`).
    """
    if profile not in ("nfw", "tnfw"):
        raise ValueError(f"profile must be 'nfw' or 'tnfw', got {profile!r}")
    if profile == "tnfw" and r_t is None:
        raise ValueError("profile 'tnfw' needs the truncation radii r_t")
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
    rr = t(radii)[None, :]
    rs, ars = t(r_s)[:, None], t(alpha_rs)[:, None]
    x2 = (rr / rs) ** 2
    if profile == "nfw":
        shape = nfw_g_over_x2(torch.sqrt(x2))
    else:
        shape = tnfw_g_over_x2(x2, t(r_t)[:, None] / rs)
    return (ars / (NFW_G1 * rs) * shape * rr).numpy()


def effective_slopes(
    profile: str, r_s, alpha_rs, r_t=None, radii=None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-halo effective slope γ_eff and signal weight ⟨α²⟩ (arcsec²) over ``radii``
    (default :func:`band_radii`). Returns two (N,) arrays."""
    radii = band_radii() if radii is None else np.asarray(radii, dtype=np.float64)
    if np.asarray(r_s).size == 0:
        return np.empty(0), np.empty(0)
    alpha = radial_deflection(profile, radii, r_s, alpha_rs, r_t)
    return 2.0 - log_slope(radii, alpha), (alpha * alpha).mean(axis=-1)


def population_slope(gamma_eff, weights, groups=None):
    """Signal-weighted mean effective slope, overall or per group.

    ``groups``: optional (N,) integer labels (e.g. the set of 13 images each subhalo
    belongs to). Returns a float, or ``(labels, slopes)`` with one slope per label.
    Groups with zero total weight get NaN.
    """
    g = np.asarray(gamma_eff, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if groups is None:
        total = w.sum()
        return float((w * g).sum() / total) if total > 0 else float("nan")
    labels, inv = np.unique(np.asarray(groups), return_inverse=True)
    num = np.bincount(inv, weights=w * g, minlength=labels.size)
    den = np.bincount(inv, weights=w, minlength=labels.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return labels, np.where(den > 0, num / den, np.nan)
