"""Cosmology, mass -> lens-parameter conversions and Dutton–Macciò concentrations."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.cosmology import FlatLambdaCDM

from subslope.physics import concentration as conc
from subslope.physics import cosmology as cos

ZL, ZS = 0.2, 0.6


def test_reference_units_planck18():
    # docs/simulation.md reference values (3 significant digits)
    assert cos.sigma_crit(ZL, ZS) == pytest.approx(4.37e10, rel=2e-3)
    assert cos.rho_crit(ZL) == pytest.approx(6.17e3, rel=2e-3)
    assert cos.arcsec_to_mpc(ZL) == pytest.approx(3.408e-3, rel=3e-4)
    assert cos.r200_arcsec(1e8, ZL) == pytest.approx(2.68, rel=2e-3)


@pytest.mark.parametrize(
    "gamma, kappa1, alpha1",
    [
        (1.01, 1.02e-2, 1.03e-2),
        (1.5, 3.26e-4, 4.34e-4),
        (2.0, 2.13e-4, 4.26e-4),
        (2.9, 3.41e-5, 6.81e-4),
    ],
)
def test_epl_amp_reference(gamma, kappa1, alpha1):
    amp = cos.epl_amp_from_m200(1e8, gamma, ZL, ZS)
    # round EPL: kappa(1") = (3-gamma)/2 A, alpha(r) = A r^(2-gamma) -> alpha(1") = A
    assert (3 - gamma) / 2 * amp == pytest.approx(kappa1, rel=5e-3)
    assert amp == pytest.approx(alpha1, rel=5e-3)


def test_epl_amp_stiff_gamma_to_one():
    ln_amp = cos.epl_log_amp_from_m200(1e8, 1.01, ZL, ZS)
    amp = cos.epl_amp_from_m200(1e8, 1.01, ZL, ZS)
    assert np.isfinite(ln_amp) and amp == pytest.approx(1.0e-2, rel=5e-2)
    theta_e = np.exp(ln_amp / (1.01 - 1.0))
    assert 0 < theta_e < 1e-190  # ~1.5e-199 arcsec in float64 ...
    assert np.float32(theta_e) == 0.0  # ... and 0 in float32: carry the amplitude instead
    # even closer to 1 the log amplitude stays finite
    assert np.isfinite(cos.epl_log_amp_from_m200(1e7, 1.0 + 1e-9, ZL, ZS))


def test_epl_amp_vectorised_and_analytic_gamma2():
    m = np.geomspace(1e7, 1e10, 7)[:, None]
    g = np.linspace(1.1, 2.9, 5)[None, :]
    amp = cos.epl_amp_from_m200(m, g, ZL, ZS)
    assert amp.shape == (7, 5) and np.all(np.isfinite(amp)) and np.all(amp > 0)
    # gamma = 2 (SIS): A = theta_E = M / (2 r200 Sigma_cr)
    sis = m[:, 0] / (2 * cos.r200_arcsec(m[:, 0], ZL) * cos.sigma_crit(ZL, ZS))
    np.testing.assert_allclose(cos.epl_amp_from_m200(m[:, 0], 2.0, ZL, ZS), sis, rtol=1e-12)
    # mass scaling at fixed gamma: A ∝ M^{1 - (3-gamma)/3}
    ratio = amp[-1] / amp[0]
    np.testing.assert_allclose(ratio, 1000.0 ** (1 - (3 - g[0]) / 3), rtol=1e-10)


def test_distances_and_cosmo_argument():
    d_l, d_s, d_ls = cos.lens_distances(ZL, ZS)
    assert d_l < d_s and 0 < d_ls < d_s
    other = FlatLambdaCDM(H0=70, Om0=0.3)
    assert cos.sigma_crit(ZL, ZS, cosmo=other) != pytest.approx(cos.sigma_crit(ZL, ZS), rel=1e-3)
    # arrays broadcast, and agree with the cached scalar path
    zs = np.array([0.2, 0.4])
    np.testing.assert_allclose(
        cos.angular_diameter_distance(zs),
        [cos.angular_diameter_distance(z) for z in zs],
        rtol=1e-12,
    )
    # rho_crit in lens-plane arcsec units = rho_crit[Msun/Mpc^3] * (Mpc per arcsec)^3
    rho_mpc = other.critical_density(0.3).to_value("Msun/Mpc3")
    assert cos.rho_crit(0.3, other) == pytest.approx(
        rho_mpc * cos.arcsec_to_mpc(0.3, other) ** 3, rel=1e-12
    )


def test_nfw_conversion_roundtrip():
    m = np.array([1e7, 1e8, 1e9, 1e10])
    c = np.array([40.0, 20.0, 12.0, 5.0])
    r_s, a_rs = cos.nfw_params_from_m200_c(m, c, ZL, ZS)
    np.testing.assert_allclose(r_s, cos.r200_arcsec(m, ZL) / c, rtol=1e-14)
    m2, c2 = cos.m200_c_from_nfw_params(r_s, a_rs, ZL, ZS)
    np.testing.assert_allclose(m2, m, rtol=1e-10)
    np.testing.assert_allclose(c2, c, rtol=1e-10)


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: cos.sigma_crit(0.6, 0.2), "z_source"),
        (lambda: cos.rho_crit(0.0), "z"),
        (lambda: cos.r200_arcsec(-1e8, ZL), "m200"),
        (lambda: cos.epl_amp_from_m200(1e8, 3.0, ZL, ZS), "gamma"),
        (lambda: cos.nfw_params_from_m200_c(1e8, -3.0, ZL, ZS), "c200"),
        (lambda: conc.dutton_maccio_c200(-1.0, 0.2), "m200"),
        (lambda: conc.dutton_maccio_c200(1e8, 0.0), "z"),
        (lambda: conc.truncation_radius_kpc(1e8, -5.0), "r_sub_kpc"),
        (
            lambda: conc.sample_c200(1e8, 0.2, np.random.default_rng(0), multiplier=0.0),
            "multiplier",
        ),
    ],
)
def test_bad_inputs_name_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call()


def test_dutton_maccio_against_colossus():
    colossus = pytest.importorskip("colossus")  # noqa: F841
    import warnings

    from colossus.cosmology import cosmology as ccosmo
    from colossus.halo import concentration as cconc

    c = ccosmo.setCosmology("planck18")
    m = np.geomspace(1e7, 1e10, 4)
    for z in (0.2, 0.5):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # DM14 is extrapolated below 1e10 Msun/h
            ref = cconc.concentration(m * c.h, "200c", z, model="dutton14")
        np.testing.assert_allclose(conc.dutton_maccio_c200(m, z, h=c.h), ref, rtol=1e-6)
    assert conc.dutton_maccio_c200(1e8, 0.2, h=c.h) == pytest.approx(18.71, rel=1e-3)


def test_dutton_maccio_trends_and_h_scaling():
    m = np.geomspace(1e7, 1e10, 10)
    c = conc.dutton_maccio_c200(m, 0.2)
    assert np.all(np.diff(c) < 0)  # lower concentration for heavier halos
    c_z = conc.dutton_maccio_c200(1e8, np.array([0.1, 0.3, 0.6]))
    assert np.all(np.diff(c_z) < 0)  # and lower at higher redshift
    # h only moves the pivot mass: c(M; h) = c(M h / h'; h')
    np.testing.assert_allclose(
        conc.dutton_maccio_c200(m, 0.2, h=0.7),
        conc.dutton_maccio_c200(m * 0.7 / 0.6, 0.2, h=0.6),
        rtol=1e-13,
    )


def test_sample_c200_scatter_and_multiplier(rng):
    m = np.full(20000, 1e8)
    c = conc.sample_c200(m, 0.2, rng, multiplier=2.0)
    dex = np.log10(c / (2.0 * conc.dutton_maccio_c200(1e8, 0.2)))
    assert abs(dex.mean()) < 3e-3 and dex.std() == pytest.approx(0.1, rel=0.03)
    np.testing.assert_allclose(
        conc.sample_c200(m[:3], 0.2, rng, scatter_dex=0.0), conc.dutton_maccio_c200(m[:3], 0.2)
    )


def test_truncation_radius():
    assert conc.truncation_radius_kpc(1e7, 50.0) == pytest.approx(1.4)
    assert conc.truncation_radius_kpc(8e7, 400.0) == pytest.approx(1.4 * 2 * 4)
    kpc = 1e3 * cos.arcsec_to_mpc(ZL)
    r_sub_arcsec = 50.0 / kpc
    assert conc.truncation_radius_arcsec(1e7, r_sub_arcsec, ZL) == pytest.approx(
        1.4 / kpc, rel=1e-12
    )
