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

__all__ = [
    "R_MIN",
    "multipole_deflection",
    "multipole_deflections",
    "multipole_convergence",
    "multipole_potential",
]

R_MIN = 1e-9


def _check(x, m, r_min) -> None:
    if not isinstance(x, Tensor) or not torch.is_floating_point(x):
        raise ValueError(f"x must be a floating-point torch.Tensor, got {type(x).__name__}")
    if not isinstance(m, int) or isinstance(m, bool) or m < 2:
        raise ValueError(f"m must be an int >= 2 (multipole order); got {m!r}")
    if not (isinstance(r_min, (int, float)) and r_min > 0):
        raise ValueError(f"r_min must be a float > 0 (arcsec); got {r_min!r}")


def _tensor(v, x: Tensor) -> Tensor:
    return v if isinstance(v, Tensor) else torch.as_tensor(v, dtype=x.dtype, device=x.device)


def _frame(x, y, cx, cy, r_min):
    """``dx, dy, r², 1/r`` and ``e^{iθ}`` about the centre."""
    cx, cy = _tensor(cx, x), _tensor(cy, x)
    dx, dy = x - cx, y - cy
    r2 = torch.clamp(dx * dx + dy * dy, min=r_min * r_min)
    inv_r = torch.rsqrt(r2)
    return dx, dy, r2, inv_r, dx * inv_r, dy * inv_r


def _angular(pr, pi, m, phi_m):
    """``cos m(θ − φ_m), sin m(θ − φ_m)`` from ``e^{imθ} = pr + i·pi``."""
    cm, sm = torch.cos(m * phi_m), torch.sin(m * phi_m)
    return pr * cm + pi * sm, pi * cm - pr * sm


def _prep(x, y, m, a_m, phi_m, cx, cy, r_min):
    _check(x, m, r_min)
    a_m, phi_m = _tensor(a_m, x), _tensor(phi_m, x)
    dx, dy, r2, inv_r, ur, ui = _frame(x, y, cx, cy, r_min)
    pr, pi = ur, ui
    for _ in range(m - 1):  # e^{i m theta}
        pr, pi = pr * ur - pi * ui, pr * ui + pi * ur
    cos_m, sin_m = _angular(pr, pi, m, phi_m)
    return a_m, dx, dy, r2, inv_r, ur, ui, cos_m, sin_m


def _deflection(ur, ui, m, a_m, cos_m, sin_m):
    k = a_m / (1 - m * m)
    a_r = k * cos_m
    a_t = -(m * k) * sin_m
    return ur * a_r - ui * a_t, ui * a_r + ur * a_t


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
    return _deflection(ur, ui, m, a_m, cos_m, sin_m)


def multipole_deflections(
    x, y, orders, a_ms, phi_ms, cx=0.0, cy=0.0, *, r_min: float = R_MIN
) -> list[tuple[Tensor, Tensor]]:
    """Deflections ``[(alpha_x, alpha_y), ...]`` of several multipoles about one centre,
    one per order of ``orders`` (increasing ints >= 2), with strengths ``a_ms`` and
    orientations ``phi_ms``: each equal bit for bit to :func:`multipole_deflection` of
    that order, the frame ``e^{iθ}`` and its powers computed once for all of them."""
    orders = list(orders)
    if any(b <= a for a, b in zip(orders, orders[1:])):
        raise ValueError(f"orders must increase, got {orders!r}")
    for m in orders:
        _check(x, m, r_min)
    dx, dy, r2, inv_r, ur, ui = _frame(x, y, cx, cy, r_min)
    out = []
    pr, pi, power = ur, ui, 1
    for m, a_m, phi_m in zip(orders, a_ms, phi_ms):
        while power < m:  # e^{i m theta}, the same recursion as for one order
            pr, pi = pr * ur - pi * ui, pr * ui + pi * ur
            power += 1
        cos_m, sin_m = _angular(pr, pi, m, _tensor(phi_m, x))
        out.append(_deflection(ur, ui, m, _tensor(a_m, x), cos_m, sin_m))
    return out


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
