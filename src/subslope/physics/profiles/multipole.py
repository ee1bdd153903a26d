r"""Circular multipole perturbation of order m >= 2 (lenstronomy ``MULTIPOLE`` convention).

Potential (Xu et al. 2013, Appendix B3, eq. B12; lenstronomy ``Multipole``), with polar
coordinates (r, theta) about the centre (cx, cy):

.. math::

    \psi = \frac{a_m}{1-m^2}\, r \cos\big(m(\theta-\phi_m)\big),\qquad
    \kappa = \tfrac12\nabla^2\psi = \frac{a_m}{2r}\cos\big(m(\theta-\phi_m)\big),

    \alpha_r = \frac{a_m}{1-m^2}\cos m(\theta-\phi_m),\qquad
    \alpha_\theta = -\frac{m\,a_m}{1-m^2}\sin m(\theta-\phi_m).

``a_m`` is dimensionless (alpha in arcsec, bounded: |alpha| <= a_m m/(m^2-1)), ``phi_m`` in
radian. The angular factors come from the
complex power ((x + i y)/r)^m (m - 1 complex multiplications), so no trigonometric
function is evaluated per pixel; only cos(m phi_m), sin(m phi_m) per profile.

Centre regularisation: r is clamped, r >= ``r_min`` (default 1e-9 arcsec). Inside that
core kappa is bounded by a_m / (2 r_min) and alpha tends to 0 at the exact centre
(alpha is bounded but direction-dependent there, so no continuous value exists).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["R_MIN", "multipole_deflection", "multipole_convergence", "multipole_potential"]

R_MIN = 1e-9


def _prep(x, y, m, a_m, phi_m, cx, cy, r_min):
    if not isinstance(x, Tensor) or not torch.is_floating_point(x):
        raise ValueError(f"x must be a floating-point torch.Tensor, got {type(x).__name__}")
    if not isinstance(m, int) or isinstance(m, bool) or m < 2:
        raise ValueError(f"m must be an int >= 2 (multipole order); got {m!r}")
    if not (isinstance(r_min, (int, float)) and r_min > 0):
        raise ValueError(f"r_min must be a float > 0 (arcsec); got {r_min!r}")
    a_m, phi_m, cx, cy = (
        v if isinstance(v, Tensor) else torch.as_tensor(v, dtype=x.dtype, device=x.device)
        for v in (a_m, phi_m, cx, cy)
    )
    dx, dy = x - cx, y - cy
    r2 = torch.clamp(dx * dx + dy * dy, min=r_min * r_min)
    inv_r = torch.rsqrt(r2)
    ur, ui = dx * inv_r, dy * inv_r  # e^{i theta}
    pr, pi = ur, ui
    for _ in range(m - 1):  # e^{i m theta}
        pr, pi = pr * ur - pi * ui, pr * ui + pi * ur
    cm, sm = torch.cos(m * phi_m), torch.sin(m * phi_m)
    # cos m(theta - phi_m), sin m(theta - phi_m)
    cos_m = pr * cm + pi * sm
    sin_m = pi * cm - pr * sm
    return a_m, dx, dy, r2, inv_r, ur, ui, cos_m, sin_m


def multipole_deflection(
    x, y, m: int, a_m, phi_m, cx=0.0, cy=0.0, *, r_min: float = R_MIN
) -> tuple[Tensor, Tensor]:
    """Deflection (alpha_x, alpha_y) in arcsec of a circular multipole of order ``m``.

    Args:
        x, y: positions (arcsec), floating tensors (they set dtype and device).
        m: multipole order, Python int >= 2.
        a_m: strength (dimensionless, as lenstronomy ``a_m``).
        phi_m: orientation (radian).
        cx, cy: centre (arcsec).
        r_min: lower clamp of the radius (arcsec).

    alpha_x = cos(theta) alpha_r - sin(theta) alpha_theta, alpha_y = sin(theta) alpha_r
    + cos(theta) alpha_theta, see the module docstring. All arguments broadcast.
    """
    a_m, dx, dy, r2, inv_r, ur, ui, cos_m, sin_m = _prep(x, y, m, a_m, phi_m, cx, cy, r_min)
    k = a_m / (1 - m * m)
    a_r = k * cos_m
    a_t = -(m * k) * sin_m
    return ur * a_r - ui * a_t, ui * a_r + ur * a_t


def multipole_convergence(
    x, y, m: int, a_m, phi_m, cx=0.0, cy=0.0, *, r_min: float = R_MIN
) -> Tensor:
    """Convergence kappa = a_m cos(m(theta - phi_m)) / (2 r) (dimensionless)."""
    a_m, dx, dy, r2, inv_r, ur, ui, cos_m, sin_m = _prep(x, y, m, a_m, phi_m, cx, cy, r_min)
    return 0.5 * a_m * cos_m * inv_r


def multipole_potential(
    x, y, m: int, a_m, phi_m, cx=0.0, cy=0.0, *, r_min: float = R_MIN
) -> Tensor:
    """Potential psi = a_m r cos(m(theta - phi_m)) / (1 - m^2) (arcsec^2)."""
    a_m, dx, dy, r2, inv_r, ur, ui, cos_m, sin_m = _prep(x, y, m, a_m, phi_m, cx, cy, r_min)
    return a_m / (1 - m * m) * cos_m * (r2 * inv_r)
