r"""Uniform convergence sheet (mass sheet), e.g. the negative sheet that removes the
mean subhalo convergence (docs/simulation.md).

.. math::

    \kappa = \kappa_0,\qquad \alpha = \kappa_0\,(x - c_x,\; y - c_y),\qquad
    \psi = \tfrac12 \kappa_0 \big((x-c_x)^2 + (y-c_y)^2\big).

kappa0 dimensionless (any sign); angles in arcsec. lenstronomy ``CONVERGENCE``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["sheet_deflection", "sheet_potential", "sheet_convergence"]


def _d(x, y, cx, cy):
    if not isinstance(x, Tensor) or not torch.is_floating_point(x):
        raise ValueError(f"x must be a floating-point torch.Tensor, got {type(x).__name__}")
    return x - cx, y - cy


def sheet_deflection(x, y, kappa0, cx=0.0, cy=0.0) -> tuple[Tensor, Tensor]:
    """Deflection kappa0 (x - cx, y - cy) in arcsec."""
    dx, dy = _d(x, y, cx, cy)
    return kappa0 * dx, kappa0 * dy


def sheet_potential(x, y, kappa0, cx=0.0, cy=0.0) -> Tensor:
    """Potential kappa0 r^2 / 2 (arcsec^2)."""
    dx, dy = _d(x, y, cx, cy)
    return 0.5 * kappa0 * (dx * dx + dy * dy)


def sheet_convergence(x, y, kappa0, cx=0.0, cy=0.0) -> Tensor:
    """Convergence kappa0 broadcast to the common shape."""
    dx, dy = _d(x, y, cx, cy)
    return kappa0 * torch.ones_like(dx)
