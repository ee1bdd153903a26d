"""Tests of the line-of-sight halo sampler (subslope.simulation.los_halos, DG19 model)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats
from scipy.special import gamma as gamma_fn

from subslope.physics import cosmology
from subslope.simulation import los_cone, los_halos

Z_L, Z_S = 0.2, 0.6


@pytest.fixture(scope="module")
def host() -> float:
    return float(los_cone.host_m200_from_epl(1.1, 2.0, Z_L, Z_S))


def _astropy_comoving(z):
    from astropy.cosmology import Planck18

    return Planck18.comoving_distance(np.asarray(z, dtype=float)).value


# ---------------------------------------------------------------------------- slices
def test_slice_grid_follows_reference():
    z_lo, z_mid = los_cone.slice_redshifts(0.6, dz=0.01)
    assert z_lo.dtype == np.float64
    assert len(z_lo) == 58
    np.testing.assert_allclose(z_lo[[0, -1]], [0.01, 0.58], atol=1e-12)
    np.testing.assert_allclose(z_mid - z_lo, 0.005, atol=1e-12)
    assert np.all(z_lo + 0.01 < 0.6)
    # off-grid source: last lower edge is the largest grid value < z_s - dz
    z_lo, _ = los_cone.slice_redshifts(0.637)
    assert z_lo[-1] == pytest.approx(0.62)
    assert los_cone.slice_redshifts(0.015)[0].size == 0


# ---------------------------------------------------------------------------- cone
def test_cone_radius_front_and_back():
    z = np.linspace(0.01, Z_S, 400)
    r = los_cone.cone_radius_arcsec(z, Z_L, Z_S, cone_diameter=4.0)
    front = z <= Z_L
    assert np.all(r[front] == 2.0)
    assert los_cone.cone_radius_arcsec(Z_L, Z_L, Z_S) == 2.0
    back = r[~front]
    assert np.all(np.diff(back) < 0) and back[0] < 2.0
    assert np.all(r > 0)
    assert los_cone.cone_radius_arcsec(Z_S, Z_L, Z_S) == pytest.approx(2.0 * (1 - 0.8), rel=1e-9)
    # the shrink factor at one redshift against independent (astropy) distances
    zq = 0.4
    d_l, d_s, d_z = _astropy_comoving([Z_L, Z_S, zq])
    expect = 2.0 * (1 - 0.8 * d_s * (d_z - d_l) / ((d_s - d_l) * d_z))
    assert los_cone.cone_radius_arcsec(zq, Z_L, Z_S) == pytest.approx(expect, rel=1e-4)
    # opening factor 0 -> a plain cylinder in angle
    assert np.all(los_cone.cone_radius_arcsec(z, Z_L, Z_S, opening_factor=0.0) == 2.0)


def test_slice_volume_against_astropy():
    cfg = los_halos.LosConfig()
    v = los_cone.slice_volumes(Z_L, Z_S, cfg)
    z_lo, z_mid = los_cone.slice_redshifts(Z_S)
    theta = los_cone.cone_radius_arcsec(z_mid, Z_L, Z_S) * math.pi / 648000
    d_lo, d_mid, d_hi = (_astropy_comoving(z) for z in (z_lo, z_mid, z_lo + 0.01))
    np.testing.assert_allclose(v, np.pi * (d_mid * theta) ** 2 * (d_hi - d_lo), rtol=2e-4)


# ---------------------------------------------------------------------------- mass function
def test_sheth_tormen_units_against_independent_formula():
    """dn/dM rebuilt from σ(R) by hand; catches h-factor and ln/lin mistakes."""
    from colossus.lss import peaks

    cosmo = los_cone.colossus_cosmology()
    h = cosmo.h
    m = np.logspace(7, 10, 7)
    for z in (0.05, 0.4):
        r = peaks.lagrangianR(m * h)  # comoving Mpc/h
        sigma = cosmo.sigma(r, z)
        dlns_dlnr = cosmo.sigma(r, z, derivative=True)
        nu2 = 0.707 * (peaks.collapseOverdensity(corrections=True, z=z) / sigma) ** 2
        f = 0.3222 * np.sqrt(2 / np.pi) * (1 + nu2**-0.3) * np.sqrt(nu2) * np.exp(-nu2 / 2)
        rho_m0 = cosmo.rho_m(0.0) * 1e9 * h**2  # comoving M☉/Mpc³
        expect = -f * rho_m0 / m**2 * dlns_dlnr / 3.0
        np.testing.assert_allclose(los_cone.sheth_tormen_dndm(m, z), expect, rtol=1e-3)
    # local slope in this range is close to the familiar ~ -1.9
    dn = los_cone.sheth_tormen_dndm(np.array([1e7, 1e10]), 0.2)
    slope = np.log(dn[1] / dn[0]) / np.log(1e3)
    assert -2.0 < slope < -1.8


def test_mass_function_integral_matches_fine_quadrature():
    m = np.logspace(7, 10, 20001)
    dn = los_cone.sheth_tormen_dndm(m, 0.3)
    expect = np.sum(0.5 * (dn[1:] + dn[:-1]) * np.diff(m))
    assert los_cone.mass_function_integral(0.3)[0] == pytest.approx(expect, rel=1e-5)


# ---------------------------------------------------------------------------- host mass
def _epl_amp(m200, gamma, z_l, z_s):
    """θ_E^(γ−1) of an EPL of mass m200 (docs/simulation.md), written out directly."""
    sigma_crit, rho_c = cosmology.sigma_crit(z_l, z_s), cosmology.rho_crit(z_l)
    r200 = (3 * m200 / (4 * np.pi * 200 * rho_c)) ** (1 / 3)
    rho0 = (3 - gamma) * m200 / (4 * np.pi * r200 ** (3 - gamma)) / sigma_crit
    pref = 2 * np.sqrt(np.pi) * gamma_fn((gamma - 1) / 2) / ((3 - gamma) * gamma_fn(gamma / 2))
    return pref * rho0


@pytest.mark.parametrize("gamma", [1.2, 2.0, 2.8])
def test_host_mass_inverts_epl_relation(gamma):
    for m in (3e11, 1e13):
        amp = _epl_amp(m, gamma, Z_L, Z_S)
        theta_e = amp ** (1 / (gamma - 1))
        assert los_cone.host_m200_from_epl(theta_e, gamma, Z_L, Z_S) == pytest.approx(m, rel=1e-9)


def test_host_mass_typical_value_and_vectorised():
    m = los_cone.host_m200_from_epl(np.array([0.9, 1.1, 1.3]), 2.0, Z_L, Z_S)
    assert m.shape == (3,) and np.all(np.diff(m) > 0)
    assert 5e12 < m[1] < 3e13  # SIS-like 1.1″ lens at z = 0.2: a group-scale host


# ---------------------------------------------------------------------------- two-halo term
def test_two_halo_boost_only_near_lens(host):
    z_lo, _ = los_cone.slice_redshifts(Z_S)
    b = los_cone.two_halo_boost(z_lo, Z_L, host)
    assert np.all(b >= 1.0)
    d = los_cone.comoving_distance
    nearest = np.abs(d(np.clip(Z_L, z_lo, z_lo + 0.01)) - d(Z_L))
    assert np.all(b[nearest >= 10.0] == 1.0)
    inside = nearest < 10.0
    assert inside.sum() >= 1 and np.all(b[inside] > 1.0)
    # a lens in the middle of a slice: only that slice is boosted (slices ~40 Mpc thick)
    b_mid = los_cone.two_halo_boost(z_lo, 0.205, host)
    assert np.flatnonzero(b_mid > 1).tolist() == [np.argmin(np.abs(z_lo - 0.2))]


def test_two_halo_boost_value_and_knobs(host):
    from colossus.lss import bias

    cosmo = los_cone.colossus_cosmology()
    z_lo = np.array([0.2])
    b = los_cone.two_halo_boost(z_lo, 0.205, host, r_min=0.5, n_quad=100)[0]
    zq = np.linspace(0.2, 0.21, 100)
    r = np.abs(_astropy_comoving(zq) - _astropy_comoving(0.205))
    r = r[r > 0.5]
    b_host = bias.haloBias(host * cosmo.h, 0.205, mdef="200c", model="tinker10")
    expect = 1 + b_host * np.mean(cosmo.correlationFunction(r * cosmo.h, 0.205))
    assert b == pytest.approx(expect, rel=2e-3)
    assert b_host > 1  # a 1e13 M☉ host is biased
    # ξ falls with r: excluding more of the centre lowers the boost
    assert los_cone.two_halo_boost(z_lo, 0.205, host, r_min=5.0)[0] < b
    # a heavier host is more biased
    assert los_cone.two_halo_boost(z_lo, 0.205, 10 * host)[0] > b
    # r_max shorter than the distance to the slice -> no boost
    far = np.array([0.22])
    assert los_cone.two_halo_boost(far, 0.205, host, r_max=10.0)[0] == 1.0
    assert los_cone.two_halo_boost(far, 0.205, host, r_max=100.0)[0] > 1.0


def test_expected_counts_two_halo_switch(host):
    on = los_halos.expected_counts(Z_L, Z_S, host, 1.0, los_halos.LosConfig(two_halo=True))
    off = los_halos.expected_counts(Z_L, Z_S, host, 1.0, los_halos.LosConfig(two_halo=False))
    z_lo, _ = los_cone.slice_redshifts(Z_S)
    ratio = on / off
    np.testing.assert_allclose(ratio, los_cone.two_halo_boost(z_lo, Z_L, host), rtol=1e-12)
    assert 1 <= np.sum(ratio > 1) <= 2


# ---------------------------------------------------------------------------- counts
def test_expected_counts_linear_in_delta_and_zero(host):
    one = los_halos.expected_counts(Z_L, Z_S, host, 1.0)
    assert one.shape == los_cone.slice_redshifts(Z_S)[0].shape and np.all(one > 0)
    np.testing.assert_allclose(
        los_halos.expected_counts(Z_L, Z_S, host, 1.7), 1.7 * one, rtol=1e-13
    )
    assert np.all(los_halos.expected_counts(Z_L, Z_S, host, 0.0) == 0.0)
    # typical system: O(10) LoS halos in a 4″ cone between 1e7 and 1e10 M☉
    assert 5 < one.sum() < 40


def test_expected_counts_scale_with_cone_area(host):
    small = los_halos.expected_counts(Z_L, Z_S, host, 1.0, los_halos.LosConfig(cone_diameter=4.0))
    big = los_halos.expected_counts(Z_L, Z_S, host, 1.0, los_halos.LosConfig(cone_diameter=8.0))
    np.testing.assert_allclose(big, 4 * small, rtol=1e-12)


def test_delta_zero_gives_empty_arrays(rng):
    halos = los_halos.sample_los(Z_L, Z_S, 1.1, 2.0, 0.0, rng)
    assert len(halos) == 0
    for a in (halos.z, halos.x, halos.y, halos.m200):
        assert a.shape == (0,) and a.dtype == np.float64


def test_poisson_totals_match_expectation(rng, host):
    n_draws = 1500
    batch = los_halos.sample_los_batch(Z_L, Z_S, 1.1, 2.0, np.full(n_draws, 1.0), rng)
    lam = los_halos.expected_counts(Z_L, Z_S, host, 1.0)
    total, expect = batch.counts.sum(), n_draws * lam.sum()
    assert abs(total - expect) < 4 * math.sqrt(expect)
    # dispersion of the per-image count is Poisson
    assert np.var(batch.counts) == pytest.approx(lam.sum(), rel=0.15)
    # per-slice occupation matches too (chi² over slices)
    _, z_mid = los_cone.slice_redshifts(Z_S)
    idx = np.searchsorted(z_mid, batch.z - 1e-9)
    occ = np.bincount(idx, minlength=len(z_mid))
    chi2 = np.sum((occ - n_draws * lam) ** 2 / (n_draws * lam))
    assert stats.chi2.sf(chi2, len(z_mid)) > 1e-4


# ---------------------------------------------------------------------------- samples
@pytest.fixture(scope="module")
def big_sample():
    rng = np.random.default_rng(7)
    cfg = los_halos.LosConfig(cone_diameter=12.0)  # 9× the volume -> ~140 halos per δ
    return los_halos.sample_los(Z_L, Z_S, 1.1, 2.0, 150.0, rng, cfg), cfg


def test_masses_follow_sheth_tormen(big_sample, host):
    halos, cfg = big_sample
    assert len(halos) > 15000
    assert halos.m200.min() >= 1e7 and halos.m200.max() <= 1e10
    # the model CDF: a λ-weighted mixture of per-slice CDFs, from a fine grid
    lam = los_halos.expected_counts(Z_L, Z_S, host, 150.0, cfg)
    _, z_mid = los_cone.slice_redshifts(Z_S)
    m = np.logspace(7, 10, 8001)
    cdf = np.zeros_like(m)
    for w, z in zip(lam, z_mid):
        dn = los_cone.sheth_tormen_dndm(m, z)
        c = np.concatenate([[0], np.cumsum(0.5 * (dn[1:] + dn[:-1]) * np.diff(m))])
        cdf += w * c / c[-1]
    cdf /= lam.sum()
    res = stats.kstest(halos.m200, lambda x: np.interp(x, m, cdf))
    assert res.pvalue > 1e-3
    # the test has power: a dn/dM ∝ M^-1.8 power law is rejected by the same sample
    s1 = -0.8

    def power_law_cdf(x):
        return (x**s1 - 1e7**s1) / (1e10**s1 - 1e7**s1)

    assert stats.kstest(halos.m200, power_law_cdf).pvalue < 1e-6


def test_positions_uniform_in_slice_disc(big_sample):
    halos, cfg = big_sample
    radius = los_cone.cone_radius_arcsec(halos.z, Z_L, Z_S, cfg.cone_diameter)
    rr = (halos.x**2 + halos.y**2) / radius**2
    assert np.all(rr <= 1.0)
    assert stats.kstest(rr, "uniform").pvalue > 1e-3
    phi = np.arctan2(halos.y, halos.x)
    assert stats.kstest(phi, stats.uniform(-np.pi, 2 * np.pi).cdf).pvalue > 1e-3
    # planes are the slice mid redshifts
    _, z_mid = los_cone.slice_redshifts(Z_S)
    assert np.all(np.isin(halos.z, z_mid))


def test_same_seed_same_output_and_batch_consistency():
    a = los_halos.sample_los(Z_L, Z_S, 1.1, 2.0, 1.3, np.random.default_rng(3))
    b = los_halos.sample_los(Z_L, Z_S, 1.1, 2.0, 1.3, np.random.default_rng(3))
    for name in ("z", "x", "y", "m200"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    params = dict(
        z_lens=[0.18, 0.22], z_source=[0.55, 0.65], theta_e=[1.0, 1.2], gamma_ml=[1.9, 2.1]
    )
    batch = los_halos.sample_los_batch(**params, delta_los=[1.0, 2.0], rng=np.random.default_rng(4))
    rng = np.random.default_rng(4)
    for i in range(2):
        single = los_halos.sample_los(*(v[i] for v in params.values()), [1.0, 2.0][i], rng)
        np.testing.assert_array_equal(batch.system(i).m200, single.m200)
        np.testing.assert_array_equal(batch.system(i).x, single.x)
    assert batch.counts.sum() == len(batch.z)


# ---------------------------------------------------------------------------- errors
@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(z_source=0.2), "z_source"),
        (dict(z_source=0.1), "z_source"),
        (dict(delta_los=-0.1), "delta_los"),
        (dict(delta_los=float("nan")), "delta_los"),
        (dict(theta_e=0.0), "theta_e"),
        (dict(gamma_ml=3.0), "gamma"),
        (dict(rng=np.random.RandomState(0)), "rng"),
    ],
)
def test_bad_inputs_name_argument(kwargs, name):
    args = dict(
        z_lens=Z_L,
        z_source=Z_S,
        theta_e=1.1,
        gamma_ml=2.0,
        delta_los=1.0,
        rng=np.random.default_rng(0),
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        los_halos.sample_los(**args)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(m_min=1e10, m_max=1e10), "m_min"),
        (dict(m_min=2e10), "m_min"),
        (dict(m_min=-1.0), "m_min"),
        (dict(dz=0.0), "dz"),
        (dict(cone_diameter=-4.0), "cone_diameter"),
        (dict(opening_factor=1.5), "opening_factor"),
        (dict(r_min=20.0), "r_max"),
    ],
)
def test_bad_config_names_key(kwargs, name):
    with pytest.raises(ValueError, match=name):
        los_halos.LosConfig(**kwargs)


def test_expected_counts_bad_inputs(host):
    with pytest.raises(ValueError, match="z_source"):
        los_halos.expected_counts(0.5, 0.5, host, 1.0)
    with pytest.raises(ValueError, match="delta_los"):
        los_halos.expected_counts(Z_L, Z_S, host, -1.0)
    with pytest.raises(ValueError, match="host_m200"):
        los_halos.expected_counts(Z_L, Z_S, 0.0, 1.0)


def test_batched_expectations_equal_one_system_at_a_time():
    """Slices, volumes and two-halo boosts of many systems evaluated together equal those
    of each system alone, bit for bit (the host bias to its last bit); per-system
    generators give each system alone."""
    zl = np.array([0.2, 0.35, 0.5])
    zs = np.array([0.6, 1.4, 0.9])
    hosts = np.array([2e12, 5e12, 1e13])
    table = los_cone.slice_table(zl, zs)
    for b in range(3):
        k = table.n[b]
        assert k == los_cone.slice_redshifts(zs[b])[0].size
        assert np.array_equal(table.volume[b, :k], los_cone.slice_volumes(zl[b], zs[b]))
        z_lo = los_cone.slice_redshifts(zs[b])[0]
        boosts = los_cone.two_halo_boosts(table.z_lo, table.n, zl, hosts)
        assert np.array_equal(boosts[b, :k], los_cone.two_halo_boost(z_lo, zl[b], hosts[b]))
        assert np.all(boosts[b, k:] == 1.0)
    # colossus' bias of an array goes through numpy's SIMD loops, which on AVX-512 CPUs
    # round the last bit of some elements differently from the one-element path
    np.testing.assert_allclose(
        los_cone.host_bias(hosts, zl),
        [los_cone.host_bias(h, z) for h, z in zip(hosts, zl)],
        rtol=4e-16,
        atol=0,
    )
    seeds = np.random.SeedSequence(3).spawn(3)
    batch = los_halos.sample_los_batch(
        zl, zs, 1.1, 2.0, 1.0, [np.random.default_rng(s) for s in seeds]
    )
    for b in range(3):
        one = los_halos.sample_los(zl[b], zs[b], 1.1, 2.0, 1.0, np.random.default_rng(seeds[b]))
        got = batch.system(b)
        assert all(
            np.array_equal(getattr(got, f), getattr(one, f)) for f in ("z", "x", "y", "m200")
        )
    with pytest.raises(ValueError, match=r"sequence of 3 of them \(one per system\), got 1 items"):
        los_halos.sample_los_batch(zl, zs, 1.1, 2.0, 1.0, [np.random.default_rng(0)])


def test_plane_logs_of_an_array_equal_the_pairs_one_at_a_time():
    zl = np.array([0.2, 0.3, 0.2, 0.45])
    zs = np.array([0.6, 0.9, 0.6, 1.2])
    rho, sig = cosmology.plane_logs(zl, zs)
    for i in range(4):
        assert (rho[i], sig[i]) == cosmology.plane_logs(float(zl[i]), float(zs[i]))
    m, g = np.array([1e8, 3e9, 2e7, 5e8]), np.array([1.5, 2.0, 2.5, 1.9])
    assert np.array_equal(
        cosmology.epl_log_amp_from_logs(m, g, rho, sig),
        cosmology.epl_log_amp_from_m200(m, g, zl, zs),
    )
