r"""External shear (lenstronomy ``SHEAR`` convention).

.. math::

    \psi = \tfrac12\gamma_1 (x^2 - y^2) + \gamma_2 x y,\qquad
    \alpha = (\gamma_1 x + \gamma_2 y,\; \gamma_2 x - \gamma_1 y),\qquad \kappa = 0,

with (x, y) measured from the origin (x0, y0) where the deflection vanishes
(lenstronomy ``ra_0, dec_0``; default 0). gamma1, gamma2 dimensionless; angles in arcsec.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["shear_deflection", "shear_potential", "shear_convergence"]


def _d(x, y, x0, y0):
    if not isinstance(x, Tensor) or not torch.is_floating_point(x):
        raise ValueError(f"x must be a floating-point torch.Tensor, got {type(x).__name__}")
    return x - x0, y - y0


def shear_deflection(x, y, gamma1, gamma2, x0=0.0, y0=0.0) -> tuple[Tensor, Tensor]:
    """Shear deflection (arcsec): alpha_x = g1 dx + g2 dy, alpha_y = g2 dx - g1 dy."""
    dx, dy = _d(x, y, x0, y0)
    return gamma1 * dx + gamma2 * dy, gamma2 * dx - gamma1 * dy


def shear_potential(x, y, gamma1, gamma2, x0=0.0, y0=0.0) -> Tensor:
    """Shear potential psi = g1 (dx^2 - dy^2)/2 + g2 dx dy (arcsec^2)."""
    dx, dy = _d(x, y, x0, y0)
    return 0.5 * gamma1 * (dx * dx - dy * dy) + gamma2 * dx * dy


def shear_convergence(x, y, gamma1, gamma2, x0=0.0, y0=0.0) -> Tensor:
    """Convergence of a pure shear: zeros broadcast to the common shape."""
    dx, dy = _d(x, y, x0, y0)
    return torch.zeros_like(gamma1 * dx + gamma2 * dy)
