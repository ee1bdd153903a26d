"""Effective subhalo slope: power laws, the NFW limits against an independent closed form,
tNFW against NFW, the concentration trend and the population weighting."""

from __future__ import annotations

import numpy as np
import pytest

from subslope.physics.effective_slope import (
    band_radii,
    effective_slopes,
    log_slope,
    population_slope,
    radial_deflection,
)
from subslope.simulation.subhalos import nfw_lens_parameters


def _nfw_alpha_closed_form(radii, r_s, alpha_rs):
    """|α|(R) of an NFW halo, Golse & Kneib (2002) eq. 13 written with arccosh/arccos."""
    x = np.asarray(radii, dtype=np.float64) / r_s
    with np.errstate(invalid="ignore"):
        big_f = np.where(
            x < 1,
            np.arccosh(1 / np.minimum(x, 1)) / np.sqrt(np.abs(1 - x * x)),
            np.arccos(1 / np.maximum(x, 1)) / np.sqrt(np.abs(x * x - 1)),
        )
    g = np.log(x / 2) + big_f
    return alpha_rs * g / x / (np.log(0.5) + 1.0)


@pytest.mark.parametrize("gamma", [1.1, 1.5, 2.0, 2.7])
def test_a_power_law_deflection_gives_its_density_slope(gamma):
    radii = band_radii()
    alpha = 0.01 * radii ** (2.0 - gamma)
    assert 2.0 - log_slope(radii, alpha) == pytest.approx(gamma, abs=1e-12)


@pytest.mark.parametrize("r_s", [1e-4, 0.03, 0.2, 1.0, 30.0])
def test_nfw_deflection_matches_the_closed_form(r_s):
    radii = band_radii(n=9)
    got = radial_deflection("nfw", radii, [r_s], [1e-3])[0]
    want = _nfw_alpha_closed_form(radii, r_s, 1e-3)
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_nfw_slope_runs_from_one_inside_r_s_to_three_outside():
    g, w = effective_slopes("nfw", [1e6, 1e3, 1.0, 1e-3, 1e-6], [1e-3] * 5)
    assert np.all(np.diff(g) > 0)
    assert 1.0 < g[0] < 1.07  # inside R_s: 1 + 1/(ln(2/x) - 1/2), x ~ 1e-7
    assert 2.9 < g[-1] < 3.0  # outside R_s: 3 - 1/ln(x/2), x ~ 1e5
    assert np.all(w > 0)


def test_tnfw_is_nfw_without_truncation_and_steeper_with_it():
    r_s, a_rs = np.full(4, 0.5), np.full(4, 1e-3)
    g_nfw, w_nfw = effective_slopes("nfw", r_s, a_rs)
    g_far, w_far = effective_slopes("tnfw", r_s, a_rs, np.full(4, 1e4))
    np.testing.assert_allclose(g_far, g_nfw, rtol=1e-6)
    np.testing.assert_allclose(w_far, w_nfw, rtol=1e-6)
    g_t, _ = effective_slopes("tnfw", r_s, a_rs, np.array([1.0, 0.3, 0.1, 1e-3]))
    assert np.all(np.diff(g_t) > 0) and np.all(g_t > g_nfw[0])
    # r_t << R << r_s: rho ~ r^-3, a logarithmically growing mass: 3 - 1/ln(R/r_t)
    assert 2.8 < g_t[-1] < 3.0
    # R >> r_s, r_t: all the mass is enclosed, a point mass (gamma 3)
    g_point, _ = effective_slopes("tnfw", [0.002], [1e-3], [0.002])
    assert g_point[0] == pytest.approx(3.0, abs=0.01)


def test_slope_rises_with_concentration_at_fixed_mass():
    mass = np.full(4, 1e9)
    c200 = 10.0 * np.array([0.5, 1.0, 4.0, 8.0])
    p = nfw_lens_parameters(mass, c200, np.array([4]), np.array([0.2]), np.array([0.6]))
    g, _ = effective_slopes("nfw", p["r_s"], p["alpha_rs"])
    assert np.all(np.diff(g) > 0)
    assert np.all((g > 1.0) & (g < 3.0))


def test_population_slope_weights_and_groups():
    g = np.array([1.0, 2.0, 3.0, 2.5])
    w = np.array([1.0, 3.0, 0.0, 0.0])
    assert population_slope(g, w) == pytest.approx(1.75)
    labels, slopes = population_slope(g, w, groups=[5, 5, 7, 7])
    assert labels.tolist() == [5, 7]
    assert slopes[0] == pytest.approx(1.75) and np.isnan(slopes[1])


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="r_min"):
        band_radii(0.4, 0.04)
    with pytest.raises(ValueError, match="profile"):
        radial_deflection("epl", band_radii(), [1.0], [1.0])
    with pytest.raises(ValueError, match="r_t"):
        radial_deflection("tnfw", band_radii(), [1.0], [1.0])
    assert [a.size for a in effective_slopes("nfw", [], [])] == [0, 0]
