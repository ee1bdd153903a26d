r"""Spherical NFW lens (Navarro, Frenk & White 1997), batched torch implementation.

Parametrisation (lenstronomy ``NFW``): scale radius ``r_s`` (*arcsec*), deflection at
the scale radius ``alpha_rs`` (*arcsec*) and centre ``(cx, cy)`` (*arcsec*). With
x = R / R_s and the lensing density normalisation
:math:`\rho_0 = \alpha_{R_s} / (4 R_s^2 g(1))`, :math:`g(1) = 1 + \ln\frac12`
(rho_0 in units of Sigma_crit per arcsec),

.. math::

    \kappa(R) = 2\rho_0 R_s\, f(x),\qquad
    \alpha(R) = 4\rho_0 R_s^2\, \frac{g(x)}{x},\qquad
    \psi(R) = 2\rho_0 R_s^3\, h(x),

(Bartelmann 1996, A&A 313, 697; Golse & Kneib 2002, A&A 390, 821, eqs. 11, 13, 54)
where, with :math:`F(x) = \operatorname{arccosh}(1/x)/\sqrt{1-x^2}` for x < 1 and
:math:`\arccos(1/x)/\sqrt{x^2-1}` for x > 1 (F(1) = 1),

.. math::

    f(x) = \frac{1 - F(x)}{x^2 - 1},\quad g(x) = \ln\frac{x}{2} + F(x),\quad
    h(x) = \ln^2\frac{x}{2} - (1 - x^2) F(x)^2 .

Numerics (all branches are evaluated on "safe" dummy inputs outside their domain, so
neither the values nor the autograd gradients carry NaN):

* Band around x = 1, :math:`|u| < 0.1` with :math:`u = 1 - x^2`: F and f are the
  power series :math:`F = \sum_k u^k/(2k+1)`, :math:`f = \sum_{k\ge1} u^{k-1}/(2k+1)`
  (both arcs share it: arctanh(s)/s and arctan(s)/s with s^2 = +-u), truncated at
  u^17 (float64) or u^9 (float32), error < 1e-17 / 1e-10 relative.
  Outside the band f = (F - 1)/u loses at most ~3 eps/|u| <= 30 eps.
* x < 1: :math:`\operatorname{arccosh}(1/x) = \ln(1 + s) - \ln x`, s = sqrt(1 - x^2),
  and g(x) is rewritten without the ln(x/2) + ln(2/x) cancellation as
  :math:`g = [x^2 L/(1+s) + \ln(1 - x^2/(2(1+s)))]/s`, L = ln(2/x); h likewise
  :math:`h = -\ell(2L + \ell)`, :math:`\ell = \ln((1+s)/2)`.
* x > 1: arccos(1/x) = arctan(s), s = sqrt(x - 1) sqrt(x + 1) (no overflow of x^2 - 1).
* Centre: x is clamped from below at ``X_MIN`` = 1e-12 (x^2 = 1e-24 is a normal
  float32). Inside that core kappa is constant (~27.6 kappa_s) and alpha falls linearly
  to exactly 0 at R = 0; alpha is computed as (alpha/R) * (dx, dy).

Shapes: every argument broadcasts with ordinary torch rules (e.g. coordinates
``(B, 1, P)`` against parameters ``(B, N, 1)``); outputs follow the dtype and device of
the broadcast inputs.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "X_MIN",
    "BAND",
    "NFW_G1",
    "nfw_F",
    "nfw_f",
    "nfw_g_over_x2",
    "nfw_h",
    "nfw_convergence",
    "nfw_deflection",
    "nfw_potential",
    "nfw_params_physical",
    "nfw_deflection_physical",
]

#: Lower clamp on x = R / R_s (dimensionless).
X_MIN = 1e-12
#: Half-width of the series band in u = 1 - x^2 around x = 1.
BAND = 0.1
#: g(1) = 1 + ln(1/2).
NFW_G1 = 1.0 + math.log(0.5)
_LN2 = math.log(2.0)


def _n_terms(dtype: torch.dtype) -> int:
    return 17 if dtype == torch.float64 else 9


def _series(u: Tensor, n: int, start: int) -> Tensor:
    """sum_{k=0}^{n-1} u^k / (2(k + start) + 1) by Horner."""
    out = torch.full_like(u, 1.0 / (2 * (start + n - 1) + 1))
    for k in range(n - 2, -1, -1):
        out = out * u + 1.0 / (2 * (start + k) + 1)
    return out


def _split(x2: Tensor):
    """Masks and safe per-branch inputs for x^2 (below / inside / above the band)."""
    u = 1.0 - x2
    lo = u >= BAND
    hi = u <= -BAND
    mid = ~(lo | hi)
    x2_lo = torch.where(lo, x2, torch.full_like(x2, 0.5))
    x2_hi = torch.where(hi, x2, torch.full_like(x2, 2.0))
    u_mid = torch.where(mid, u, torch.zeros_like(u))
    return lo, mid, hi, x2_lo, x2_hi, u_mid


def _parts(x2: Tensor):
    """Per-branch pieces shared by F, f, g, h.

    Returns masks, s_lo = sqrt(1 - x^2) on x < 1, s_hi = sqrt(x^2 - 1) on x > 1,
    F on each branch.
    """
    lo, mid, hi, x2_lo, x2_hi, u_mid = _split(x2)
    s_lo = torch.sqrt(1.0 - x2_lo)
    F_lo = (torch.log1p(s_lo) - 0.5 * torch.log(x2_lo)) / s_lo
    s_hi = torch.sqrt(x2_hi - 1.0)
    F_hi = torch.atan(s_hi) / s_hi
    F_mid = _series(u_mid, _n_terms(x2.dtype), 0)
    return lo, mid, hi, x2_lo, x2_hi, u_mid, s_lo, s_hi, F_lo, F_mid, F_hi


def _x2_of(x: Tensor) -> Tensor:
    return torch.clamp(x * x, min=X_MIN**2)


def nfw_F(x: Tensor) -> Tensor:
    """F(x) = arccosh(1/x)/sqrt(1-x^2) (x<1), arccos(1/x)/sqrt(x^2-1) (x>1), F(1) = 1.

    Dimensionless; x = R/R_s >= 0 (clamped at ``X_MIN``).
    """
    lo, mid, hi, *_, F_lo, F_mid, F_hi = _parts(_x2_of(x))
    return torch.where(lo, F_lo, torch.where(hi, F_hi, F_mid))


def _f_from_parts(x2, parts):
    lo, mid, hi, x2_lo, x2_hi, u_mid, s_lo, s_hi, F_lo, F_mid, F_hi = parts
    f_lo = (F_lo - 1.0) / (1.0 - x2_lo)
    f_hi = (1.0 - F_hi) / (x2_hi - 1.0)
    f_mid = _series(u_mid, _n_terms(x2.dtype) - 1, 1)
    return torch.where(lo, f_lo, torch.where(hi, f_hi, f_mid))


def _g_over_x2_from_parts(x2, parts):
    lo, mid, hi, x2_lo, x2_hi, u_mid, s_lo, s_hi, F_lo, F_mid, F_hi = parts
    # x < 1: g/x^2 = [L/(1+s) + log1p(y)/x^2]/s, y = -x^2/(2(1+s)); log1p(y)/x^2 =
    # log1p(y)/y * (-1/(2(1+s))) with |y| <= 1/4 (y never underflows: x^2 >= 1e-24).
    big_l = _LN2 - 0.5 * torch.log(x2_lo)
    one_s = 1.0 + s_lo
    y = -x2_lo / (2.0 * one_s)
    g2_lo = (big_l / one_s + torch.log1p(y) / x2_lo) / s_lo
    g2_mid = (0.5 * torch.log(1.0 - u_mid) - _LN2 + F_mid) / (1.0 - u_mid)
    g2_hi = (0.5 * torch.log(x2_hi) - _LN2 + F_hi) / x2_hi
    return torch.where(lo, g2_lo, torch.where(hi, g2_hi, g2_mid))


def nfw_f(x: Tensor) -> Tensor:
    """Convergence shape f(x) = (1 - F(x))/(x^2 - 1); kappa = 2 rho_0 R_s f(x).

    f(1) = 1/3; f ~ ln(2/x) - 1 for x -> 0; f ~ 1/x^2 for x -> inf.
    """
    x2 = _x2_of(x)
    return _f_from_parts(x2, _parts(x2))


def nfw_g_over_x2(x: Tensor) -> Tensor:
    """g(x)/x^2 with g(x) = ln(x/2) + F(x) (projected mass: M_2D(<R) = 4 pi rho_0 R_s^3 g).

    alpha / R = 4 rho_0 R_s g(x)/x^2. Tends to ln(2/x)/2 - 1/4 for x -> 0.
    """
    x2 = _x2_of(x)
    return _g_over_x2_from_parts(x2, _parts(x2))


def nfw_h(x: Tensor) -> Tensor:
    """Potential shape h(x) = ln^2(x/2) - (1 - x^2) F(x)^2; psi = 2 rho_0 R_s^3 h(x).

    Normalised so that h(0) = 0 (lenstronomy convention); dh/dx = 2 g(x)/x.
    """
    x2 = _x2_of(x)
    lo, mid, hi, x2_lo, x2_hi, u_mid, s_lo, s_hi, F_lo, F_mid, F_hi = _parts(x2)
    ell = torch.log1p(-x2_lo / (2.0 * (1.0 + s_lo)))  # ln((1+s)/2)
    big_l = _LN2 - 0.5 * torch.log(x2_lo)
    h_lo = -ell * (2.0 * big_l + ell)
    h_mid = (0.5 * torch.log(1.0 - u_mid) - _LN2) ** 2 - u_mid * F_mid**2
    h_hi = (0.5 * torch.log(x2_hi) - _LN2) ** 2 + (x2_hi - 1.0) * F_hi**2
    return torch.where(lo, h_lo, torch.where(hi, h_hi, h_mid))


def _x2_from_coords(dx: Tensor, dy: Tensor, r_s: Tensor) -> Tensor:
    return torch.clamp((dx * dx + dy * dy) / (r_s * r_s), min=X_MIN**2)


def nfw_convergence(x: Tensor, y: Tensor, r_s: Tensor, alpha_rs: Tensor, cx, cy) -> Tensor:
    r"""NFW convergence :math:`\kappa = 2\rho_0 R_s f(R/R_s)`,
    :math:`2\rho_0 R_s = \alpha_{R_s}/(2 R_s g(1))` (Golse & Kneib 2002, eq. 11).

    Args (broadcastable tensors, *Unit: arcsec*): image-plane ``x``, ``y``; scale radius
    ``r_s`` (> 0); deflection at the scale radius ``alpha_rs``; centre ``cx``, ``cy``.
    Returns dimensionless kappa.
    """
    x2 = _x2_from_coords(x - cx, y - cy, r_s)
    f = _f_from_parts(x2, _parts(x2))
    return alpha_rs / (2.0 * NFW_G1 * r_s) * f


def nfw_deflection(
    x: Tensor, y: Tensor, r_s: Tensor, alpha_rs: Tensor, cx, cy
) -> tuple[Tensor, Tensor]:
    r"""NFW deflection :math:`\vec\alpha = 4\rho_0 R_s\,\frac{g(x)}{x^2}\,(\Delta x, \Delta y)`
    (radial magnitude :math:`4\rho_0R_s^2 g(x)/x`, Golse & Kneib 2002, eq. 13), so that
    :math:`|\alpha|(R_s) = \alpha_{R_s}`.

    Args as :func:`nfw_convergence`. Returns ``(alpha_x, alpha_y)``, *Unit: arcsec*;
    exactly 0 at the centre.
    """
    dx, dy = x - cx, y - cy
    x2 = _x2_from_coords(dx, dy, r_s)
    a_over_r = alpha_rs / (NFW_G1 * r_s) * _g_over_x2_from_parts(x2, _parts(x2))
    return a_over_r * dx, a_over_r * dy


def nfw_potential(x: Tensor, y: Tensor, r_s: Tensor, alpha_rs: Tensor, cx, cy) -> Tensor:
    r"""NFW lensing potential :math:`\psi = 2\rho_0R_s^3 h(x) = \frac{\alpha_{R_s}R_s}{2g(1)}h(x)`
    (Golse & Kneib 2002, eq. 54; zero at the centre). *Unit: arcsec^2.*
    """
    h = nfw_h(torch.sqrt(_x2_from_coords(x - cx, y - cy, r_s)))
    return alpha_rs * r_s / (2.0 * NFW_G1) * h


def nfw_params_physical(
    m200, c200, z_lens: float, z_source: float, like: Tensor, cosmo=None
) -> tuple[Tensor, Tensor]:
    """``(r_s, alpha_rs)`` tensors (arcsec) from numpy/array ``m200`` (M_sun) and ``c200``
    via :func:`subslope.physics.cosmology.nfw_params_from_m200_c` (float64), cast to the dtype and
    device of ``like``.
    """
    from subslope.physics.cosmology import nfw_params_from_m200_c

    r_s, alpha_rs = nfw_params_from_m200_c(
        np.asarray(m200), np.asarray(c200), z_lens, z_source, cosmo
    )
    return (
        torch.as_tensor(r_s, dtype=like.dtype, device=like.device),
        torch.as_tensor(alpha_rs, dtype=like.dtype, device=like.device),
    )


def nfw_deflection_physical(
    x: Tensor, y: Tensor, m200, c200, cx, cy, z_lens: float, z_source: float, cosmo=None
) -> tuple[Tensor, Tensor]:
    """NFW deflection (arcsec) of halos given by ``m200`` (M_sun, 200 rho_crit(z_lens)) and
    ``c200`` (numpy or tensors; they must broadcast with ``x`` after conversion, e.g. shape
    ``(B, N, 1)`` against coordinates ``(B, 1, P)``).
    """
    r_s, alpha_rs = nfw_params_physical(m200, c200, z_lens, z_source, like=x, cosmo=cosmo)
    return nfw_deflection(x, y, r_s, alpha_rs, cx, cy)
