r"""Truncated NFW lens (Baltz, Marshall & Oguri 2009, JCAP 01, 015), batched torch.

3-D density :math:`\rho = \rho_{NFW}(r)\,\frac{r_t^2}{r^2 + r_t^2}` (BMO09 eq. 2.3 with
n = 1). Parametrisation (lenstronomy ``TNFW``): ``r_s``, ``alpha_rs`` (the deflection
at R_s of the *untruncated* NFW with the same rho_0), truncation radius ``r_trunc``
and centre ``cx, cy``, all in *arcsec*. With x = R/R_s, tau = r_t/R_s,
:math:`\rho_0 = \alpha_{R_s}/(4R_s^2(1+\ln\frac12))`, :math:`Q = \sqrt{\tau^2+x^2}`,
:math:`L = \ln\frac{x}{\tau + Q}` and F(x) the NFW function of
:mod:`subslope.physics.profiles.nfw`, BMO09 eqs. A.5 and A.6 read

.. math::

    \kappa = 2\rho_0R_s\frac{\tau^2}{(\tau^2+1)^2}\Big[(\tau^2+1)f(x) + 2F(x)
        - \frac{\pi}{Q} + \frac{\tau^2-1}{\tau Q}L\Big],

    \frac{\alpha}{R} = \frac{4\rho_0R_s}{x^2}\frac{\tau^2}{(\tau^2+1)^2}\Big[
        (\tau^2+1+2(x^2-1))F + \pi\tau + (\tau^2-1)\ln\tau
        + Q\big(\frac{\tau^2-1}{\tau}L - \pi\big)\Big],

with f(x) = (1 - F)/(x^2 - 1) the NFW convergence shape.

Rearrangement used for the deflection (exact algebra, removes the cancellations of
O(tau^2 ln(1/x)) terms at small x and of O(x) terms at large x, so no limit branch
is needed for tau -> infinity or tau -> 0): with g(x) = ln(x/2) + F(x) (NFW),

.. math::

    [\dots] = (\tau^2-1)\,I + J,\quad
    I = g(x) - \ln\Big(1 + \frac{x^2}{2\tau(\tau+Q)}\Big) + \frac{x^2 L}{\tau(\tau+Q)},\quad
    J = x^2\Big(2F - \frac{\pi}{\tau+Q}\Big),

and for x >= 2, :math:`J = \frac{x^2}{s}\big[\pi\frac{\tau + (\tau^2+1)/(Q+s)}{\tau+Q}
- 2\arctan\frac1s\big]`, s = sqrt(x^2 - 1). The logarithm is evaluated as
:math:`L = -\mathrm{log1p}\big(\tau(1 + \tau/(Q+x))/x\big)` (accurate when L -> 0).
As tau -> infinity, I -> g and J/tau^2 -> 0, so alpha -> alpha_NFW.

Convergence at large radius: the bracket of kappa cancels down to O(x^-4) from O(x^-1)
terms, so for x > ``X_ASYMP`` * max(1, tau) (10 in float64, 3 in float32) kappa is the convergent
expansion
:math:`\kappa = 2\rho_0R_s\,\frac{\tau^2}{2}\sum_n a_n x^{-4-n} w_n`, where
:math:`\hat\rho = \tau^2 r^{-5}(1+1/r)^{-2}(1+\tau^2/r^2)^{-1} = \tau^2\sum a_n r^{-5-n}`
and each power is projected exactly,
:math:`\int r^{-p}dz = x^{1-p}\sqrt\pi\,\Gamma(\frac{p-1}{2})/\Gamma(\frac p2)`.
The a_n x^-n follow the recurrence of (1+y)^2(1+tau^2 y^2) = 1 + 2y + (1+tau^2)y^2
+ 2 tau^2 y^3 + tau^2 y^4 (terms shrink by a factor >= 10 (float64, 18 terms) or
>= 3 (float32, 24 terms)).

Centre: x is clamped at :data:`subslope.physics.profiles.nfw.X_MIN` = 1e-12 as for the NFW.
Domain: tau in [1e-3, 1e4] is tested (float32 and float64); x up to 1e6.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from subslope.physics.profiles.nfw import (
    NFW_G1,
    X_MIN,
    _f_from_parts,
    _g_over_x2_from_parts,
    _parts,
)

__all__ = [
    "X_ASYMP",
    "tnfw_convergence",
    "tnfw_deflection",
    "tnfw_kappa_shape",
    "tnfw_g_over_x2",
    "series_weights",
    "kappa_asymptotic",
]

#: kappa switches to the large-radius expansion beyond X_ASYMP[dtype] * max(1, tau):
#: float64 10 (18 terms), float32 3 (24 terms; the direct form loses ~eps x^3 there).
X_ASYMP = {torch.float64: 10.0, torch.float32: 3.0}
_PI = math.pi


def series_weights(n: int) -> list[float]:
    # w_n = sqrt(pi) Gamma((n+4)/2) / Gamma((n+5)/2)
    return [
        math.exp(0.5 * math.log(math.pi) + math.lgamma((k + 4) / 2) - math.lgamma((k + 5) / 2))
        for k in range(n)
    ]


_W64 = series_weights(18)
_W32 = series_weights(24)


def _log_ratio(x: Tensor, tau: Tensor, q: Tensor) -> Tensor:
    """L = ln(x / (tau + Q)) = -log1p(tau (1 + tau/(Q + x)) / x)."""
    return -torch.log1p(tau * (1.0 + tau / (q + x)) / x)


def _prefactor(tau: Tensor) -> Tensor:
    """tau^2 / (tau^2 + 1)^2 without forming tau^4."""
    return (tau / (tau * tau + 1.0)) ** 2


def tnfw_g_over_x2(x2: Tensor, tau: Tensor) -> Tensor:
    """BMO09 projected-mass shape over x^2 (dimensionless): alpha/R = 4 rho_0 R_s * this.

    ``x2`` = (R/R_s)^2 (already clamped >= X_MIN^2), ``tau`` = r_t/R_s > 0.
    """
    parts = _parts(x2)
    lo, mid, hi, x2_lo, x2_hi, u_mid, s_lo, s_hi, F_lo, F_mid, F_hi = parts
    F = torch.where(lo, F_lo, torch.where(hi, F_hi, F_mid))
    g2 = _g_over_x2_from_parts(x2, parts)
    x = torch.sqrt(x2)
    t2 = tau * tau
    q = torch.sqrt(t2 + x2)
    tq = tau * (tau + q)
    z = x2 / (2.0 * tq)
    # log1p(z)/z, guarded for z -> 0
    tiny = z < 1e-7
    z_safe = torch.where(tiny, torch.ones_like(z), z)
    l1p_over_z = torch.where(tiny, 1.0 - 0.5 * z, torch.log1p(z_safe) / z_safe)
    big_l = _log_ratio(x, tau, q)
    i2 = g2 - l1p_over_z / (2.0 * tq) + big_l / tq
    # J / x^2
    j2_near = 2.0 * F - _PI / (tau + q)
    far = x2 >= 4.0
    x2_far = torch.where(far, x2, torch.full_like(x2, 4.0))
    s = torch.sqrt(x2_far - 1.0)
    q_far = torch.sqrt(t2 + x2_far)
    j2_far = (
        _PI * (tau + (t2 + 1.0) / (q_far + s)) / (tau + q_far) - 2.0 * torch.atan(1.0 / s)
    ) / s
    j2 = torch.where(far, j2_far, j2_near)
    return _prefactor(tau) * ((t2 - 1.0) * i2 + j2)


def kappa_asymptotic(x2: Tensor, tau: Tensor, weights: list[float]) -> Tensor:
    """(1/2) tau^2 x^-4 sum_n w_n a_n x^-n for x > max(1, tau) (see module docstring)."""
    x2s = torch.clamp(x2, min=1.0)  # branch only used for x >= 10 max(1, tau)
    uu = torch.rsqrt(x2s)  # 1/x
    v = tau * tau / x2s  # tau^2/x^2
    u2 = uu * uu
    c = [torch.ones_like(uu)]
    total = weights[0] * c[0]
    for n in range(1, len(weights)):
        cn = -2.0 * uu * c[n - 1]
        if n >= 2:
            cn = cn - (u2 + v) * c[n - 2]
        if n >= 3:
            cn = cn - 2.0 * uu * v * c[n - 3]
        if n >= 4:
            cn = cn - v * u2 * c[n - 4]
        c.append(cn)
        total = total + weights[n] * cn
    return 0.5 * v * u2 * total


def tnfw_kappa_shape(x2: Tensor, tau: Tensor) -> Tensor:
    """BMO09 convergence shape: kappa = 2 rho_0 R_s * this (dimensionless)."""
    parts = _parts(x2)
    lo, mid, hi, x2_lo, x2_hi, u_mid, s_lo, s_hi, F_lo, F_mid, F_hi = parts
    F = torch.where(lo, F_lo, torch.where(hi, F_hi, F_mid))
    f = _f_from_parts(x2, parts)
    x = torch.sqrt(x2)
    t2 = tau * tau
    q = torch.sqrt(t2 + x2)
    big_l = _log_ratio(x, tau, q)
    direct = _prefactor(tau) * ((t2 + 1.0) * f + 2.0 * F - _PI / q + (t2 - 1.0) / (tau * q) * big_l)
    f64 = x2.dtype == torch.float64
    asym = kappa_asymptotic(x2, tau, _W64 if f64 else _W32)
    big = X_ASYMP[torch.float64 if f64 else torch.float32] * torch.clamp(tau, min=1.0)
    return torch.where(x2 > big * big, asym, direct)


def _x2_tau(dx, dy, r_s, r_trunc):
    # plain Python numbers are accepted for the parameters
    kw = dict(dtype=dx.dtype, device=dx.device)
    r_s = torch.as_tensor(r_s, **kw)
    x2 = torch.clamp((dx * dx + dy * dy) / (r_s * r_s), min=X_MIN**2)
    tau = torch.as_tensor(r_trunc, **kw) / r_s
    x2, tau = torch.broadcast_tensors(x2, tau)
    return x2, tau


def tnfw_convergence(
    x: Tensor, y: Tensor, r_s: Tensor, alpha_rs: Tensor, r_trunc: Tensor, cx, cy
) -> Tensor:
    r"""Truncated-NFW convergence (BMO09 eq. A.5, lenstronomy ``TNFW`` parameters).

    Args (broadcastable tensors, *Unit: arcsec*): ``x, y`` image-plane positions;
    ``r_s`` scale radius (> 0); ``alpha_rs`` NFW deflection at R_s (sets rho_0);
    ``r_trunc`` truncation radius (> 0); centre ``cx, cy``. Returns kappa
    (dimensionless).
    """
    x2, tau = _x2_tau(x - cx, y - cy, r_s, r_trunc)
    return alpha_rs / (2.0 * NFW_G1 * r_s) * tnfw_kappa_shape(x2, tau)


def tnfw_deflection(
    x: Tensor, y: Tensor, r_s: Tensor, alpha_rs: Tensor, r_trunc: Tensor, cx, cy
) -> tuple[Tensor, Tensor]:
    r"""Truncated-NFW deflection (BMO09 eq. A.6, rearranged; see module docstring).

    Args as :func:`tnfw_convergence`. Returns ``(alpha_x, alpha_y)``, *Unit: arcsec*;
    exactly 0 at the centre; tends to the NFW deflection as r_trunc/r_s -> infinity.
    """
    dx, dy = x - cx, y - cy
    x2, tau = _x2_tau(dx, dy, r_s, r_trunc)
    a_over_r = alpha_rs / (NFW_G1 * r_s) * tnfw_g_over_x2(x2, tau)
    return a_over_r * dx, a_over_r * dy
