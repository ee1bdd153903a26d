r"""Elliptical power-law (EPL) mass profile, batched torch implementation.

Convergence (lenstronomy ``EPL`` convention), in the frame centred on ``(cx, cy)`` and
rotated by the position angle ``phi`` (see :mod:`subslope.physics.profiles.ellipse`):

.. math::

    \kappa(x', y') = \frac{3-\gamma}{2}
        \left(\frac{\theta_E}{\sqrt{q x'^2 + y'^2/q}}\right)^{\gamma-1}
      = \frac{2-t}{2}\,A\,q^{t/2}\,R^{-t},
    \qquad t = \gamma - 1,\; R = |Z|,\; Z = q x' + i y',

parametrised by the **amplitude** ``amp`` :math:`A = \theta_E^{\gamma-1}`
(*Unit: arcsec^(gamma-1)*). Subhalos with gamma -> 1 have A ~ 1e-2 while
theta_E ~ 1e-199 arcsec, so A is carried instead of theta_E; ``theta_e_to_amp``
converts in log space.

Deflection: Tessore & Metcalf (2015, A&A 580, A79), eqs. (13) and (23)-(29),

.. math::

    \alpha_x' + i\alpha_y' = \frac{2}{1+q}\,A\,q^{t/2}\,R^{-t}\; Z\;
        {}_2F_1\!\left(1, \tfrac{t}{2}; 2-\tfrac{t}{2}; -f e^{2i\varphi}\right),
    \qquad f = \frac{1-q}{1+q} = e,\; e^{2i\varphi} = Z^2/R^2 .

The hypergeometric function is summed as its power series in u = -f e^{2i phi}
(|u| = e <= 0.283 in the prior, so the series converges geometrically) with term ratio
a_n / a_{n-1} = (2n - 2 + t) / (2n + 2 - t) (TM15 eq. 29). The ``n_terms`` first terms
are kept; the neglected tail is bounded by e^n_terms / (1 - e) relative to |alpha|.
The polynomial of real coefficients is evaluated at the complex point u with Goertzel's
two-term recurrence (2 real multiply-adds per term; Knuth TAOCP 4.6.4), which needs only
Re u per pixel because |u|^2 = e^2 is a profile parameter. No trigonometric function
is evaluated per pixel.

Potential: psi = (dx alpha_x + dy alpha_y) / (3 - gamma) (Euler's theorem for a
profile homogeneous of degree 3 - gamma; TM15 eq. 15).

Centre regularisation: R is clamped from below, R >= ``r_min`` (default 1e-9 arcsec,
far below any pixel or supersampling scale, and R_MIN^2 = 1e-18 is a normal float32).
Inside that tiny core kappa is constant and alpha falls linearly to 0 at the exact
centre, so every output is finite and continuous (kappa <= 1.0e18 A for gamma = 2.99).
"""

from __future__ import annotations

import torch
from torch import Tensor

from subslope.physics.profiles.ellipse import ellipse_frame

__all__ = [
    "N_TERMS_DEFAULT",
    "R_MIN",
    "theta_e_to_amp",
    "amp_to_theta_e",
    "epl_convergence",
    "epl_deflection",
    "epl_deflection_and_convergence",
    "series_coefficients",
    "epl_potential",
    "epl_convergence_theta_e",
    "epl_deflection_theta_e",
]

#: Default number of series terms; truncation error <= 1.2e-7 |alpha| over the
#: prior (e1, e2 in [-0.2, 0.2], gamma in [1.01, 2.99]); measured in docs/physics.md (EPL).
N_TERMS_DEFAULT = 14
#: Lower clamp (arcsec) of the elliptical radius R = |q x' + i y'|.
R_MIN = 1e-9


def _ref(x) -> Tensor:
    if not isinstance(x, Tensor) or not torch.is_floating_point(x):
        raise ValueError(
            f"x must be a floating-point torch.Tensor, got {type(x).__name__}"
            + (f" of dtype {x.dtype}" if isinstance(x, Tensor) else "")
        )
    return x


def _as(v, ref: Tensor) -> Tensor:
    if isinstance(v, Tensor):
        return v
    return torch.as_tensor(v, dtype=ref.dtype, device=ref.device)


def _check_params(gamma: Tensor, amp: Tensor, e1: Tensor, e2: Tensor) -> None:
    if not bool(((gamma >= 1) & (gamma < 3)).all()):
        bad = gamma[~((gamma >= 1) & (gamma < 3))].flatten()[0].item()
        raise ValueError(f"gamma must lie in [1, 3); got {bad}")
    if not bool((amp >= 0).all()):
        bad = amp[~(amp >= 0)].flatten()[0].item()
        raise ValueError(f"amp must be >= 0 (amp = theta_E**(gamma-1)); got {bad}")
    e_sq = e1 * e1 + e2 * e2
    if not bool((e_sq < 1).all()):
        raise ValueError(
            "e1, e2 must satisfy e1**2 + e2**2 < 1 (axis ratio q > 0); "
            f"got e = {e_sq.max().sqrt().item()}"
        )


def _check_knobs(n_terms, r_min) -> None:
    if not isinstance(n_terms, int) or isinstance(n_terms, bool) or n_terms < 1:
        raise ValueError(f"n_terms must be an int >= 1; got {n_terms!r}")
    if not (isinstance(r_min, (int, float)) and r_min > 0):
        raise ValueError(f"r_min must be a float > 0 (arcsec); got {r_min!r}")


def theta_e_to_amp(theta_e, gamma) -> Tensor:
    """Amplitude ``A = theta_E**(gamma - 1)`` computed as ``exp((gamma-1) ln theta_E)``.

    *Unit*: theta_e in arcsec; result in arcsec^(gamma-1). theta_e = 0 gives 0.
    """
    ref = theta_e if isinstance(theta_e, Tensor) else gamma
    ref = (
        ref
        if isinstance(ref, Tensor)
        else torch.as_tensor(theta_e, dtype=torch.get_default_dtype())
    )
    theta_e, gamma = _as(theta_e, ref), _as(gamma, ref)
    if not bool((theta_e >= 0).all()):
        raise ValueError(f"theta_e must be >= 0 arcsec; got {theta_e.min().item()}")
    pos = theta_e > 0
    log_t = torch.log(torch.where(pos, theta_e, torch.ones_like(theta_e)))
    return torch.where(pos, torch.exp((gamma - 1) * log_t), torch.zeros_like(log_t))


def amp_to_theta_e(amp, gamma) -> Tensor:
    """Einstein radius ``theta_E = A**(1/(gamma-1))`` (arcsec); underflows to 0 as gamma -> 1."""
    ref = amp if isinstance(amp, Tensor) else gamma
    ref = ref if isinstance(ref, Tensor) else torch.as_tensor(amp, dtype=torch.get_default_dtype())
    amp, gamma = _as(amp, ref), _as(gamma, ref)
    return torch.exp(torch.log(amp) / (gamma - 1))


def _frame(x, y, e1, e2, cx, cy):
    q, c, s = ellipse_frame(e1, e2)
    dx, dy = x - cx, y - cy
    X = (q * c) * dx + (q * s) * dy  # q x'
    Y = c * dy - s * dx  # y'
    return q, c, s, dx, dy, X, Y


def epl_convergence(
    x, y, amp, gamma, e1, e2, cx=0.0, cy=0.0, *, r_min: float = R_MIN, validate: bool = True
) -> Tensor:
    r"""EPL convergence :math:`\kappa = \frac{3-\gamma}{2} A q^{(\gamma-1)/2} R^{1-\gamma}`.

    Args:
        x, y: positions (arcsec), floating tensors; they set dtype and device.
        amp: amplitude A = theta_E**(gamma-1) (arcsec^(gamma-1)), >= 0.
        gamma: 3-D logarithmic density slope, in [1, 3).
        e1, e2: ellipticity components (lenstronomy convention), e < 1.
        cx, cy: centre (arcsec).
        r_min: lower clamp of R = |q x' + i y'| (arcsec).
        validate: check parameter ranges (costs a host sync on GPU).

    All arguments broadcast together. *Unit*: dimensionless.
    """
    x = _ref(x)
    amp, gamma, e1, e2, cx, cy = (_as(v, x) for v in (amp, gamma, e1, e2, cx, cy))
    _check_knobs(1, r_min)
    if validate:
        _check_params(gamma, amp, e1, e2)
    q, c, s, dx, dy, X, Y = _frame(x, y, e1, e2, cx, cy)
    t = gamma - 1
    R2 = torch.clamp(X * X + Y * Y, min=r_min * r_min)
    pref = (0.5 * (3 - gamma)) * amp * torch.pow(q, 0.5 * t)
    return pref * torch.pow(R2, -0.5 * t)


def series_coefficients(gamma: Tensor, n_terms: int) -> list[Tensor]:
    """Coefficients a_0..a_{n-1} of 2F1(1, t/2; 2 - t/2; u) = sum a_n u^n (a_0 = 1)."""
    t = gamma - 1
    coeffs = [torch.ones_like(t)]
    for n in range(1, n_terms):
        coeffs.append(coeffs[-1] * (2 * n - 2 + t) / (2 * n + 2 - t))
    return coeffs


def epl_deflection_and_convergence(
    x,
    y,
    amp,
    gamma,
    e1,
    e2,
    cx=0.0,
    cy=0.0,
    *,
    n_terms: int = N_TERMS_DEFAULT,
    r_min: float = R_MIN,
    validate: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    r"""EPL deflection and convergence ``(alpha_x, alpha_y, kappa)`` sharing one evaluation.

    Deflection (arcsec) from Tessore & Metcalf (2015, eq. 13/29):
    :math:`\alpha' = \frac{2}{1+q} A q^{t/2} R^{-t} Z\,{}_2F_1(1, t/2; 2-t/2; -f Z^2/R^2)`
    in the profile frame (Z = q x' + i y', t = gamma - 1, f = (1-q)/(1+q)), rotated
    back to the sky; kappa as :func:`epl_convergence`. Arguments as
    :func:`epl_convergence`; ``n_terms`` is the number of hypergeometric-series terms
    kept (relative truncation error <= e**n_terms/(1-e)). The convergence costs one
    extra multiply, which the renderer uses for the negative mass sheet.
    """
    x = _ref(x)
    amp, gamma, e1, e2, cx, cy = (_as(v, x) for v in (amp, gamma, e1, e2, cx, cy))
    _check_knobs(n_terms, r_min)
    if validate:
        _check_params(gamma, amp, e1, e2)
    q, c, s, dx, dy, X, Y = _frame(x, y, e1, e2, cx, cy)
    t = gamma - 1
    f = (1 - q) / (1 + q)
    R2 = torch.clamp(X * X + Y * Y, min=r_min * r_min)
    inv_r2 = 1.0 / R2
    # u = -f e^{2i phi}; only Re(u) is needed per pixel, |u|^2 = f^2 is a parameter.
    ur = (X * X - Y * Y) * ((-f) * inv_r2)
    s2 = 2 * ur
    m = f * f
    a = series_coefficients(gamma, n_terms)
    # Goertzel: b_k = a_k + s2 b_{k+1} - m b_{k+2};  p(u) = a_0 - m b_2 + u b_1.
    b1 = torch.zeros_like(ur) + a[-1] if n_terms > 1 else torch.zeros_like(ur)
    b2 = torch.zeros_like(b1)
    for k in range(n_terms - 2, 0, -1):
        b1, b2 = a[k] + s2 * b1 - m * b2, b1
    Fr = 1 + ur * b1 - m * b2
    # Im(u) b1 with Im(u) = -f 2 X Y / R2
    Fi = (X * Y) * ((-2 * f) * inv_r2) * b1
    amp_q = amp * torch.pow(q, 0.5 * t)
    r_pow = torch.pow(R2, -0.5 * t)
    scale = ((2 / (1 + q)) * amp_q) * r_pow
    ax_f = scale * (X * Fr - Y * Fi)
    ay_f = scale * (X * Fi + Y * Fr)
    kappa = ((0.5 * (3 - gamma)) * amp_q) * r_pow
    return c * ax_f - s * ay_f, s * ax_f + c * ay_f, kappa


def epl_deflection(
    x,
    y,
    amp,
    gamma,
    e1,
    e2,
    cx=0.0,
    cy=0.0,
    *,
    n_terms: int = N_TERMS_DEFAULT,
    r_min: float = R_MIN,
    validate: bool = True,
) -> tuple[Tensor, Tensor]:
    """EPL deflection (alpha_x, alpha_y) in arcsec (Tessore & Metcalf 2015, eq. 13/29).

    See :func:`epl_deflection_and_convergence`. For a round profile
    alpha = A r^(2-gamma) r_hat.
    """
    ax, ay, _ = epl_deflection_and_convergence(
        x, y, amp, gamma, e1, e2, cx, cy, n_terms=n_terms, r_min=r_min, validate=validate
    )
    return ax, ay


def epl_potential(
    x,
    y,
    amp,
    gamma,
    e1,
    e2,
    cx=0.0,
    cy=0.0,
    *,
    n_terms: int = N_TERMS_DEFAULT,
    r_min: float = R_MIN,
    validate: bool = True,
) -> Tensor:
    """EPL lensing potential psi = (dx alpha_x + dy alpha_y)/(3 - gamma) (arcsec^2; TM15 eq. 15)."""
    x = _ref(x)
    ax, ay = epl_deflection(
        x, y, amp, gamma, e1, e2, cx, cy, n_terms=n_terms, r_min=r_min, validate=validate
    )
    gamma, cx, cy = _as(gamma, x), _as(cx, x), _as(cy, x)
    return ((x - cx) * ax + (y - cy) * ay) / (3 - gamma)


def epl_convergence_theta_e(x, y, theta_e, gamma, e1, e2, cx=0.0, cy=0.0, **kwargs) -> Tensor:
    """:func:`epl_convergence` parametrised by the Einstein radius theta_e (arcsec), for the main
    lens."""
    return epl_convergence(
        x, y, theta_e_to_amp(_as(theta_e, _ref(x)), _as(gamma, x)), gamma, e1, e2, cx, cy, **kwargs
    )


def epl_deflection_theta_e(
    x, y, theta_e, gamma, e1, e2, cx=0.0, cy=0.0, **kwargs
) -> tuple[Tensor, Tensor]:
    """:func:`epl_deflection` parametrised by the Einstein radius theta_e (arcsec), for the main
    lens."""
    return epl_deflection(
        x, y, theta_e_to_amp(_as(theta_e, _ref(x)), _as(gamma, x)), gamma, e1, e2, cx, cy, **kwargs
    )
