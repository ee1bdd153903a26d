"""How many subhalos a CDM host projects into the image: the expected count of a
power-law subhalo mass function normalised by a projected number density.

The form is the one of pyHalo and paltas (Gilman et al. 2020, MNRAS 491, 6077;
Wagner-Carena et al. 2023, ApJ 942, 75):

.. math:: \\frac{d^2N}{dm\\,dA} = \\Sigma_{\\rm sub}\\, m_p^{-1}
          \\left(\\frac{m}{m_p}\\right)^{\\alpha},

with Σ_sub in kpc⁻², the pivot mass m_p (M☉) and the slope α, so that

.. math:: N = \\Sigma_{\\rm sub}\\, A\\, m_p^{-\\alpha-1}
          \\frac{m_{\\max}^{\\alpha+1} - m_{\\min}^{\\alpha+1}}{\\alpha+1}

subhalos of mass in [m_min, m_max] fall on the projected area A (kpc²). paltas trains
on Σ_sub ~ N(2·10⁻³, 1.1·10⁻³) kpc⁻² at m_p = 10¹⁰ M☉, α ≈ −1.9, m in [10⁷, 10¹⁰] M☉
and no host-mass scaling (its ``config_train.py`` of arXiv:2203.00690), a prior
centred on what its SLACS analysis then inferred. Pure functions; float64.
"""

from __future__ import annotations

import numpy as np

from subslope.physics.cosmology import arcsec_to_mpc

__all__ = [
    "PALTAS_SIGMA_SUB",
    "PALTAS_PIVOT",
    "expected_count",
    "field_area_kpc2",
    "uniform_count_max",
]

#: paltas's training prior on Σ_sub (kpc⁻²): mean and standard deviation.
PALTAS_SIGMA_SUB = (2.0e-3, 1.1e-3)
#: paltas's pivot mass of Σ_sub, M☉.
PALTAS_PIVOT = 1.0e10


def expected_count(sigma_sub, area_kpc2, *, slope=-1.9, m_min=1e7, m_max=1e10, m_pivot=1e10):
    """Expected number of subhalos with mass in ``[m_min, m_max]`` (M☉) on ``area_kpc2``
    (kpc²) for the normalisation ``sigma_sub`` (kpc⁻², at ``m_pivot``) and mass-function
    slope ``slope`` (≠ −1): the module's equation for N."""
    if not 0 < m_min < m_max:
        raise ValueError(f"need 0 < m_min < m_max, got {m_min!r}, {m_max!r}")
    if slope == -1.0:
        raise ValueError("slope = -1 needs the logarithmic form")
    k = slope + 1.0
    integral = (m_max**k - m_min**k) / k
    return np.asarray(sigma_sub, dtype=np.float64) * area_kpc2 * m_pivot ** (-k) * integral


def field_area_kpc2(side_arcsec: float, z_lens, cosmo=None) -> np.ndarray:
    """Area (kpc²) of a square field of side ``side_arcsec`` at the lens redshift."""
    kpc = 1e3 * arcsec_to_mpc(z_lens, cosmo) * side_arcsec
    return kpc**2


def uniform_count_max(z_lens: float, field_arcsec: float, cosmo=None) -> tuple[float, ...]:
    """The N_max of a count prior U{0, N_max} whose mean, N_max / 2, equals the expected
    count of a host at ``z_lens`` in a square field of side ``field_arcsec`` for paltas's
    Σ_sub prior: ``(mean − 1σ, mean, mean + 1σ)`` of Σ_sub, mass function as the scenes'
    (slope −1.9 on [10⁷, 10¹⁰] M☉, pivot 10¹⁰ M☉)."""
    area = float(field_area_kpc2(field_arcsec, z_lens, cosmo))
    mean, sd = PALTAS_SIGMA_SUB
    return tuple(
        2.0 * float(expected_count(s, area, m_pivot=PALTAS_PIVOT))
        for s in (mean - sd, mean, mean + sd)
    )
