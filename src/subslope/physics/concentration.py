r"""Subhalo concentrations (Dutton & Macciò 2014) and tNFW truncation radii (numpy).

Concentration–mass relation for c200 (200 rho_crit), Dutton & Macciò (2014, MNRAS
441, 3359), eqs. 10–11 with the Planck NFW fit of their Table 3, extrapolated to
subhalo masses as in docs/simulation.md:

.. math::

    \log_{10} c_{200} = A(z) + B(z)\,\log_{10}\frac{M_{200}}{10^{12}\,h^{-1} M_\odot},
    \quad A = 0.520 + 0.385\,e^{-0.617 z^{1.21}},\quad B = -0.101 + 0.026\,z .

Truncation radius of tNFW subhalos (docs/simulation.md; the reference analysis' recipe):

.. math::

    r_t = 1.4\,\mathrm{kpc}\,(M_{200}/10^7 M_\odot)^{1/3}\,(r_{sub}/50\,\mathrm{kpc})^{2/3},

with r_sub the projected distance of the subhalo from the lens centre.
"""

from __future__ import annotations

import numpy as np

from subslope.physics.cosmology import _check_positive, arcsec_to_mpc

__all__ = [
    "DM14_H",
    "dutton_maccio_c200",
    "sample_c200",
    "truncation_radius_kpc",
    "truncation_radius_arcsec",
]

#: Little h used in the mass pivot 1e12 h^-1 M_sun of the Dutton–Macciò fit.
DM14_H = 0.7


def dutton_maccio_c200(m200, z, h: float = DM14_H) -> np.ndarray:
    """Median c200 of Dutton & Macciò (2014) for ``m200`` (M_sun, physical, 200 rho_crit)
    at redshift ``z`` (> 0). ``h`` sets the pivot mass 1e12/h M_sun (default 0.7).

    Dimensionless; broadcasts over ``m200`` and ``z``.
    """
    m200 = _check_positive("m200", m200)
    z = _check_positive("z", z)
    h = float(_check_positive("h", h))
    a = 0.520 + 0.385 * np.exp(-0.617 * z**1.21)
    b = -0.101 + 0.026 * z
    return 10.0 ** (a + b * np.log10(m200 * h / 1e12))


def sample_c200(
    m200,
    z,
    rng: np.random.Generator,
    multiplier: float = 1.0,
    scatter_dex: float = 0.1,
    h: float = DM14_H,
) -> np.ndarray:
    """Draw c200 = ``multiplier`` x c_DM14(m200, z) x 10^N(0, ``scatter_dex``).

    ``multiplier`` is the concentration multiplier *a* of the paper's CDM tests
    (a = 1: CDM). ``rng`` is a numpy Generator (one normal per element of the
    broadcast shape of ``m200`` and ``z``). ``scatter_dex = 0`` returns the median.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator; got {type(rng).__name__}")
    multiplier = float(_check_positive("multiplier", multiplier))
    scatter_dex = float(scatter_dex)
    if not np.isfinite(scatter_dex) or scatter_dex < 0:
        raise ValueError(f"scatter_dex must be finite and >= 0; got {scatter_dex}")
    c = multiplier * dutton_maccio_c200(m200, z, h)
    if scatter_dex > 0:
        c = c * 10.0 ** rng.normal(0.0, scatter_dex, size=np.shape(c))
    return c


def truncation_radius_kpc(m200, r_sub_kpc) -> np.ndarray:
    """tNFW truncation radius 1.4 kpc (M200/1e7 M_sun)^(1/3) (r_sub/50 kpc)^(2/3).

    ``r_sub_kpc``: projected distance from the lens centre (physical kpc, > 0).
    *Unit: physical kpc.*
    """
    m200 = _check_positive("m200", m200)
    r_sub = _check_positive("r_sub_kpc", r_sub_kpc)
    return 1.4 * np.cbrt(m200 / 1e7) * np.cbrt(r_sub / 50.0) ** 2


def truncation_radius_arcsec(m200, r_sub_arcsec, z_lens, cosmo=None) -> np.ndarray:
    """Truncation radius in lens-plane arcsec, for a subhalo at projected distance
    ``r_sub_arcsec`` (arcsec, > 0) from the lens centre at redshift ``z_lens``.

    Converts r_sub to kpc with :func:`subslope.physics.cosmology.arcsec_to_mpc`, applies
    :func:`truncation_radius_kpc`, converts back. *Unit: arcsec.*
    """
    kpc_per_arcsec = 1e3 * arcsec_to_mpc(z_lens, cosmo)
    r_sub_kpc = _check_positive("r_sub_arcsec", r_sub_arcsec) * kpc_per_arcsec
    return truncation_radius_kpc(m200, r_sub_kpc) / kpc_per_arcsec
