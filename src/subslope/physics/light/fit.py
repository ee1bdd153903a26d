"""PSF-convolved elliptical Sérsic fit of a lens galaxy's light, many images at once.

Model of one image (e⁻/s per pixel): the elliptical Sérsic of
:func:`subslope.physics.light.sersic.sersic_ellipse_from_magnitude` at the pixel centres
(× pixel area, as the renderer draws the lens light), convolved with the PSF
(:func:`subslope.physics.instrument.convolve`). Parameters per image::

    θ = (mag, ln R_s, n, e1, e2, x, y, b)   (AB mag, ln arcsec, -, -, -, arcsec, arcsec, e⁻/s)

with ``b`` a constant pedestal per pixel: the sky level that the cutouts' sky subtraction
left (0.05–0.24 e⁻/s on the 13 HST lenses). Fitted by default (``pedestal=True``), the
same on real and simulated images; without it a 4″ cutout turns the pedestal into Sérsic
wings, R_s runs to the box edge and the magnitude 1–3 mag too bright (docs/realism.md).
Fit: weighted least squares, χ² = Σ_p w_p (d_p − m_p(θ))², with w_p = mask_p / σ_p² and
σ_p² = σ_bg² + max(d_p, 0) / t + (s·max(d_p, 0))² (background, the data's Poisson term
and a model-error floor ``s`` = ``systematic``, so that a real galaxy's departures from
one Sérsic in its bright core do not dominate). The arcs are masked: an annulus
``arc_mask`` × θ_E about the lens centre is left out, and after a first fit the pixels
more than ``clip`` σ above the model (the rest of the arcs, other galaxies) are masked
too (dilated by one pixel) before the fit is repeated.

Solver: Levenberg–Marquardt (Marquardt 1963), all images of a batch stepped together,
each with its own damping λ; parameters are kept in their box (:data:`BOUNDS`) after
every step. The Jacobian columns of the two linear parameters are exact (∂m/∂mag =
−0.4 ln 10 (m − b), ∂m/∂b = 1), the others forward differences. The model is evaluated
in ``dtype`` (float64, the reference; float32 is ~4× cheaper on a CPU, with difference
steps of ~√ε of float32), the normal equations are solved in float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import ZERO_POINT, convolve, kernel_spectrum
from subslope.physics.light.sersic import e1e2_to_q_phi, sersic_ellipse_from_magnitude

__all__ = [
    "BOUNDS",
    "PARAMS",
    "JOINT_BOX",
    "LightFit",
    "sersic_model",
    "fit_lens_light",
    "prior_from_fits",
    "joint_prior_from_fits",
    "sky_prior_from_fits",
]

#: Fitted parameters, in the order of θ.
PARAMS = ("mag", "ln_r", "n", "e1", "e2", "x", "y", "b")
#: Box of each parameter (the centre's is relative to its starting value). R_s ≤ 10″
#: (~33 kpc at z = 0.2): beyond it a 4″ cutout cannot bound R_s, which then trades
#: against n and the pedestal.
BOUNDS = {
    "mag": (5.0, 35.0),
    "ln_r": (math.log(0.02), math.log(10.0)),
    "n": (0.3, 10.0),
    "e1": (-0.8, 0.8),
    "e2": (-0.8, 0.8),
    "x": (-0.3, 0.3),
    "y": (-0.3, 0.3),
    "b": (-0.2, 1.0),
}
#: Forward-difference steps of the non-linear parameters, by model dtype.
_STEPS = {
    torch.float64: torch.tensor([0.0, 1e-4, 1e-4, 1e-5, 1e-5, 1e-5, 1e-5, 0.0]),
    torch.float32: torch.tensor([0.0, 1e-3, 1e-3, 3e-4, 3e-4, 3e-4, 3e-4, 0.0]),
}
_LN10 = math.log(10.0)


@dataclass
class LightFit:
    """Fitted lens light of ``B`` images (arrays ``(B,)``) and its model ``(B, H, W)``.

    ``mag`` (AB), ``r_sersic`` (arcsec), ``n_sersic``, ``e1``, ``e2``, ``q`` (axis ratio),
    ``x``, ``y`` (arcsec), ``background`` (e⁻/s per pixel), ``chi2_dof`` (χ² per unmasked
    pixel), ``mask`` (pixels used,
    ``(B, H, W)`` bool), ``model`` and ``sigma`` (the σ_p map, e⁻/s)."""

    mag: np.ndarray
    r_sersic: np.ndarray
    n_sersic: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    q: np.ndarray
    x: np.ndarray
    y: np.ndarray
    background: np.ndarray
    chi2_dof: np.ndarray
    mask: np.ndarray
    model: np.ndarray
    sigma: np.ndarray


def sersic_model(
    theta: torch.Tensor, grid, psf: torch.Tensor, pixel_scale: float, spectrum=None
) -> torch.Tensor:
    """PSF-convolved Sérsic images plus pedestal, ``(B, H, W)``, of ``theta`` ``(B, 8)``
    (``spectrum``: the PSF's :func:`~subslope.physics.instrument.kernel_spectrum`)."""
    xs, ys = grid
    p = [theta[:, k, None, None] for k in range(8)]
    sb = sersic_ellipse_from_magnitude(
        xs, ys, p[0], torch.exp(p[1]), p[2], p[3], p[4], p[5], p[6], zero_point=ZERO_POINT
    )
    return convolve(sb * pixel_scale**2, psf, spectrum=spectrum) + p[7]


def _clamp(theta: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    lo = torch.tensor([BOUNDS[k][0] for k in PARAMS], dtype=theta.dtype)
    hi = torch.tensor([BOUNDS[k][1] for k in PARAMS], dtype=theta.dtype)
    lo = lo.expand_as(theta).clone()
    hi = hi.expand_as(theta).clone()
    lo[:, 5:7] += start[:, 5:7]
    hi[:, 5:7] += start[:, 5:7]
    out = torch.minimum(torch.maximum(theta, lo), hi)
    e = torch.hypot(out[:, 3], out[:, 4])
    shrink = torch.clamp(0.8 / torch.clamp(e, min=1e-12), max=1.0)
    out[:, 3] *= shrink
    out[:, 4] *= shrink
    return out


def _chi2(model, data, weight) -> torch.Tensor:
    return ((data - model) ** 2 * weight).double().sum((-2, -1))


def _column(k: int, theta, model, grid, psf, pixel_scale, spectrum, steps) -> torch.Tensor:
    """∂model/∂θ_k ``(B, H, W)``: exact for mag and b, else a forward difference."""
    if k == 0:
        return -0.4 * _LN10 * (model - theta[:, 7, None, None])
    if k == 7:
        return torch.ones_like(model)
    t = theta.clone()
    t[:, k] += steps[k]
    return (sersic_model(t, grid, psf, pixel_scale, spectrum) - model) / steps[k]


def _lm(theta, data, weight, grid, psf, pixel_scale, iterations: int, free, spectrum=None):
    """Levenberg–Marquardt steps of every image of the batch (module docstring); only the
    parameters ``free`` move."""
    start = theta.clone()
    steps = _STEPS[theta.dtype].to(theta.dtype)
    lam = torch.full((theta.shape[0],), 1e-2, dtype=torch.float64)
    model = sersic_model(theta, grid, psf, pixel_scale, spectrum)
    chi2 = _chi2(model, data, weight)
    b = theta.shape[0]
    idx = torch.nonzero(free).reshape(-1).tolist()
    npar = len(idx)
    eye = torch.eye(npar, dtype=torch.float64)
    for _ in range(iterations):
        cols = [_column(k, theta, model, grid, psf, pixel_scale, spectrum, steps) for k in idx]
        jac = torch.stack([c.reshape(b, -1) for c in cols], -1)  # (B, P, free parameters)
        w = weight.reshape(b, -1, 1)
        a = ((jac * w).transpose(1, 2) @ jac).double()
        g = ((jac * w).transpose(1, 2) @ (data - model).reshape(b, -1, 1))[..., 0].double()
        diag = torch.diagonal(a, dim1=1, dim2=2).clamp(min=1e-12)
        step = torch.linalg.solve(a + (lam[:, None] * diag)[:, :, None] * eye, g)
        full = torch.zeros_like(theta)
        full[:, idx] = step.to(theta.dtype)
        trial = _clamp(theta + full, start)
        m_trial = sersic_model(trial, grid, psf, pixel_scale, spectrum)
        c_trial = _chi2(m_trial, data, weight)
        better = torch.isfinite(c_trial) & (c_trial < chi2)
        theta = torch.where(better[:, None], trial, theta)
        model = torch.where(better[:, None, None], m_trial, model)
        chi2 = torch.where(better, c_trial, chi2)
        lam = torch.where(better, lam / 3.0, lam * 4.0).clamp(1e-9, 1e9)
    return theta, model, chi2


def _start(data, grid, centres, pixel_scale: float) -> torch.Tensor:
    """Starting θ: magnitude of the flux within 2″, R_s = 1″, n = 3, round, at ``centres``."""
    xs, ys = grid
    r = torch.hypot(xs - centres[:, 0, None, None], ys - centres[:, 1, None, None])
    flux = (data * (r < 2.0)).sum((-2, -1)).clamp(min=1e-3)
    mag = ZERO_POINT - 2.5 * torch.log10(flux)
    b = data.shape[0]
    theta = torch.zeros(b, len(PARAMS), dtype=torch.float64)
    theta[:, 0], theta[:, 1], theta[:, 2] = mag, 0.0, 3.0
    theta[:, 5:7] = centres
    return theta


def _checked_images(images) -> torch.Tensor:
    data = torch.as_tensor(np.asarray(images, dtype=np.float64))
    if data.ndim != 3:
        raise ValueError(f"images must be (B, H, W), got shape {tuple(data.shape)}")
    if not torch.all(torch.isfinite(data)):
        raise ValueError("images contain NaN or Inf")
    if data.shape[1] != data.shape[2]:
        raise ValueError(f"images must be square, got {data.shape[1]} x {data.shape[2]}")
    return data


def fit_lens_light(
    images,
    psf,
    centres,
    theta_e,
    *,
    background_sigma: float,
    exposure_time: float,
    pixel_scale: float,
    arc_mask: tuple[float, float] = (0.6, 1.5),
    clip: float | None = 3.0,
    systematic: float = 0.02,
    iterations: int = 10,
    pedestal: bool = True,
    dtype: torch.dtype = torch.float64,
) -> LightFit:
    """Fit the lens light of ``images`` ``(B, H, W)`` (e⁻/s per pixel) with the arcs masked.

    ``psf``: the pixel kernel (odd, sum 1); ``centres``: ``(B, 2)`` starting lens centres
    (x, y, arcsec); ``theta_e``: ``(B,)`` Einstein radii (arcsec) for the arc annulus
    ``arc_mask`` (inner, outer, in units of θ_E); ``background_sigma``: the detector's
    empty-pixel σ (e⁻/s); ``exposure_time`` (s) for the Poisson term; ``clip``: the
    second pass masks pixels this many σ above the first model (``None``: one pass);
    ``systematic``: the model-error floor ``s`` of σ_p (module docstring);
    ``iterations``: LM steps per pass; ``pedestal``: fit the constant ``b`` too;
    ``dtype``: of the model evaluations (module docstring).
    """
    if dtype not in _STEPS:
        raise ValueError(f"dtype must be torch.float64 or torch.float32, got {dtype}")
    data = _checked_images(images)
    b, h, w = data.shape
    psf_t = torch.as_tensor(np.asarray(psf, dtype=np.float64))
    xs, ys = pixel_grid(h, pixel_scale, dtype=torch.float64)
    grid = (xs[None], ys[None])
    c = torch.as_tensor(np.asarray(centres, dtype=np.float64)).reshape(b, 2)
    te = torch.as_tensor(np.asarray(theta_e, dtype=np.float64)).reshape(b)
    r = torch.hypot(xs[None] - c[:, 0, None, None], ys[None] - c[:, 1, None, None])
    lo, hi = arc_mask
    mask = ~((r > lo * te[:, None, None]) & (r < hi * te[:, None, None]))
    pos = data.clamp(min=0)
    sigma = torch.sqrt(background_sigma**2 + pos / exposure_time + (systematic * pos) ** 2)
    theta = _start(data, grid, c, pixel_scale).to(dtype)
    free = torch.ones(len(PARAMS), dtype=torch.bool)
    free[7] = pedestal
    grid_d = (grid[0].to(dtype), grid[1].to(dtype))
    psf_d = psf_t.to(dtype)
    spectrum = kernel_spectrum(psf_d, (h, w))
    data_d = data.to(dtype)

    def solve(theta, mask):
        weight = (mask / sigma**2).to(dtype)
        return _lm(theta, data_d, weight, grid_d, psf_d, pixel_scale, iterations, free, spectrum)

    theta, model, chi2 = solve(theta, mask)
    if clip is not None:
        hot = (data - model.double()) > clip * sigma
        hot = torch.nn.functional.max_pool2d(hot[:, None].double(), 3, 1, 1)[:, 0] > 0
        mask = mask & ~hot
        theta, model, chi2 = solve(theta, mask)
    theta, model = theta.double(), model.double()
    q, _ = e1e2_to_q_phi(theta[:, 3], theta[:, 4])
    npix = mask.sum((-2, -1)).clamp(min=1)
    return LightFit(
        mag=theta[:, 0].numpy(),
        r_sersic=torch.exp(theta[:, 1]).numpy(),
        n_sersic=theta[:, 2].numpy(),
        e1=theta[:, 3].numpy(),
        e2=theta[:, 4].numpy(),
        q=q.numpy(),
        x=theta[:, 5].numpy(),
        y=theta[:, 6].numpy(),
        background=theta[:, 7].numpy(),
        chi2_dof=(chi2 / npix).numpy(),
        mask=mask.numpy(),
        model=model.numpy(),
        sigma=sigma.numpy(),
    )


def prior_from_fits(
    mag,
    r_sersic,
    n_sersic,
    q,
    *,
    mag_margin: float = 0.5,
    r_factor: float = 1.25,
    n_margin: float = 0.5,
    e_margin: float = 0.05,
    decimals: int = 2,
) -> dict[str, dict[str, float | str]]:
    """Uniform lens-light priors covering fitted values with a margin (config mappings).

    ``mag``: U(min − mag_margin, max + mag_margin); ``r_sersic``: U(min / r_factor,
    max · r_factor) within the fit's box (:data:`BOUNDS`); ``n_sersic``: U(min − n_margin,
    max + n_margin) clipped to [0.5, 8]; ``e1``, ``e2``: U(−e, e) with
    e = max (1 − q)/(1 + q) + e_margin. Bounds
    are rounded outwards to ``decimals``."""
    mag, r, n, q = (np.asarray(v, dtype=np.float64) for v in (mag, r_sersic, n_sersic, q))
    scale = 10.0**decimals

    def uniform(lo, hi):
        return {
            "dist": "uniform",
            "low": float(math.floor(lo * scale) / scale),
            "high": float(math.ceil(hi * scale) / scale),
        }

    e = float(np.max((1 - q) / (1 + q))) + e_margin
    r_box = round(math.exp(BOUNDS["ln_r"][1]), 9)
    return {
        "mag": uniform(mag.min() - mag_margin, mag.max() + mag_margin),
        "r_sersic": uniform(r.min() / r_factor, min(r.max() * r_factor, r_box)),
        "n_sersic": uniform(max(0.5, n.min() - n_margin), min(8.0, n.max() + n_margin)),
        "e1": uniform(-e, e),
        "e2": uniform(-e, e),
    }


#: Box of the joint lens-light prior (:func:`joint_prior_from_fits`): AB mag, ln R_s
#: (R_s in 0.05–8″: 8″ is ~26 kpc at z = 0.2, twice the largest of the 13 HST fits),
#: Sérsic index and axis ratio.
JOINT_BOX = {
    "low": {"mag": 10.0, "ln_r": round(math.log(0.05), 4), "n": 0.5, "q": 0.2},
    "high": {"mag": 25.0, "ln_r": round(math.log(8.0), 4), "n": 8.0, "q": 1.0},
}


#: Fewest fits a joint lens-light prior is made from (:func:`joint_prior_from_fits`):
#: a 4 × 4 sample covariance needs at least 5 points to be of full rank.
MIN_JOINT_FITS = 5


def joint_prior_from_fits(
    mag, r_sersic, n_sersic, q, *, widen: float = 1.5, digits: int = 5
) -> dict[str, object]:
    """The joint lens-light prior of fitted values (a config mapping of
    :class:`subslope.simulation.priors.JointNormal`): the sample mean and covariance of
    (mag, ln R_s, n, q) (``ddof = 1``), standard deviations times ``widen``, in
    :data:`JOINT_BOX`; numbers rounded to ``digits`` significant digits."""
    x = np.stack([np.asarray(v, dtype=np.float64) for v in (mag, np.log(r_sersic), n_sersic, q)])
    if x.shape[1] < MIN_JOINT_FITS:
        raise ValueError(f"a joint prior needs at least {MIN_JOINT_FITS} fits, got {x.shape[1]}")

    def sig(v: float) -> float:
        return float(f"{v:.{digits}g}")

    names = ("mag", "ln_r", "n", "q")
    cov = np.cov(x, ddof=1)
    return {
        "mean": {k: sig(m) for k, m in zip(names, x.mean(axis=1), strict=True)},
        "cov": [[sig(v) for v in row] for row in cov],
        "widen": float(widen),
        "low": dict(JOINT_BOX["low"]),
        "high": dict(JOINT_BOX["high"]),
    }


def sky_prior_from_fits(background, *, widen: float = 1.5, digits: int = 3) -> dict[str, object]:
    """The sky-level prior of fitted pedestals (e⁻/s per pixel): a normal of their mean
    and ``widen`` × their standard deviation (``ddof = 1``) truncated at 0, as a config
    mapping."""
    b = np.asarray(background, dtype=np.float64)
    return {
        "dist": "normal",
        "mean": float(f"{b.mean():.{digits}g}"),
        "std": float(f"{widen * b.std(ddof=1):.{digits}g}"),
        "low": 0.0,
    }
