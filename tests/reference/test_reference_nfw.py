"""Cross-checks of the NFW / tNFW profiles and unit conversions against lenstronomy 1.14.2.

Tolerances: Sigma_crit and the NFW angle conversions differ by 2.8e-4 relative because
lenstronomy uses older constants (G = 6.67384e-11, M_sun = 1.9891e30) than astropy's
CODATA 2018 / IAU 2015 values; we assert rtol 1e-3. Profiles agree to rtol 1e-9 (float64)
for x = R/R_s >= 1e-2 (lenstronomy's TNFW clamps x at 1e-3 and its NFW deflection at
R = 1e-8).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.physics import cosmology as cos
from subslope.physics.profiles import nfw, tnfw

pytestmark = pytest.mark.reference

ZL, ZS = 0.2, 0.6


def _lenstronomy():
    from astropy.cosmology import Planck18
    from lenstronomy.Cosmo.lens_cosmo import LensCosmo

    return LensCosmo(ZL, ZS, cosmo=Planck18)


def test_sigma_crit_and_nfw_conversion_vs_lenscosmo():
    lc = _lenstronomy()
    assert cos.sigma_crit(ZL, ZS) == pytest.approx(lc.sigma_crit_angle, rel=1e-3)
    assert cos.arcsec_to_mpc(ZL) == pytest.approx(lc.arcsec2phys_lens(1.0), rel=1e-10)
    for m, c in [(1e7, 35.0), (1e8, 18.7), (1e9, 12.0), (1e10, 7.0)]:
        rs_ref, ars_ref = lc.nfw_physical2angle(m, c)
        rs, ars = cos.nfw_params_from_m200_c(m, c, ZL, ZS)
        assert rs == pytest.approx(rs_ref, rel=1e-3)
        assert ars == pytest.approx(ars_ref, rel=1e-3)
        assert cos.r200_arcsec(m, ZL) == pytest.approx(lc.nfw_M_theta_r200(m), rel=1e-3)


def _grid(rng, r_s, n=60):
    # log-uniform radii in [1e-2, 50] R_s, random directions, off-centre halo
    rad = r_s * 10 ** rng.uniform(-2, np.log10(50), n)
    phi = rng.uniform(0, 2 * np.pi, n)
    cx, cy = 0.13, -0.07
    return cx + rad * np.cos(phi), cy + rad * np.sin(phi), cx, cy


@pytest.mark.parametrize("r_s, alpha_rs", [(0.05, 1e-3), (0.3, 2e-2), (1.5, 0.5)])
def test_nfw_vs_lenstronomy(r_s, alpha_rs, rng):
    from lenstronomy.LensModel.Profiles.nfw import NFW

    x, y, cx, cy = _grid(rng, r_s)
    ref = NFW()
    ax_ref, ay_ref = ref.derivatives(x, y, r_s, alpha_rs, cx, cy)
    fxx, _, _, fyy = ref.hessian(x, y, r_s, alpha_rs, cx, cy)
    pot_ref = ref.function(x, y, r_s, alpha_rs, cx, cy)
    t = lambda v: torch.as_tensor(v, dtype=torch.float64)  # noqa: E731
    args = (t(x), t(y), t(r_s), t(alpha_rs), cx, cy)
    ax, ay = nfw.nfw_deflection(*args)
    np.testing.assert_allclose(ax.numpy(), ax_ref, rtol=1e-9, atol=1e-14 * alpha_rs)
    np.testing.assert_allclose(ay.numpy(), ay_ref, rtol=1e-9, atol=1e-14 * alpha_rs)
    np.testing.assert_allclose(nfw.nfw_convergence(*args).numpy(), 0.5 * (fxx + fyy), rtol=1e-9)
    np.testing.assert_allclose(nfw.nfw_potential(*args).numpy(), pot_ref, rtol=1e-9, atol=1e-14)


@pytest.mark.parametrize("tau", [1e-2, 0.3, 1.0, 5.0, 30.0, 1e3])
@pytest.mark.parametrize("r_s, alpha_rs", [(0.05, 1e-3), (0.8, 0.1)])
def test_tnfw_vs_lenstronomy(r_s, alpha_rs, tau, rng):
    from lenstronomy.LensModel.Profiles.tnfw import TNFW

    x, y, cx, cy = _grid(rng, r_s)
    ref = TNFW()
    r_t = tau * r_s
    ax_ref, ay_ref = ref.derivatives(x, y, r_s, alpha_rs, r_t, cx, cy)
    fxx, _, _, fyy = ref.hessian(x, y, r_s, alpha_rs, r_t, cx, cy)
    t = lambda v: torch.as_tensor(v, dtype=torch.float64)  # noqa: E731
    args = (t(x), t(y), t(r_s), t(alpha_rs), t(r_t), cx, cy)
    ax, ay = tnfw.tnfw_deflection(*args)
    scale = np.max(np.hypot(ax_ref, ay_ref))
    np.testing.assert_allclose(ax.numpy(), ax_ref, rtol=1e-8, atol=1e-12 * scale)
    np.testing.assert_allclose(ay.numpy(), ay_ref, rtol=1e-8, atol=1e-12 * scale)
    # lenstronomy's closed-form kappa cancels catastrophically far outside max(R_s, r_t)
    # (see tnfw module docstring); compare with an absolute floor there.
    k_ref = 0.5 * (fxx + fyy)
    np.testing.assert_allclose(
        tnfw.tnfw_convergence(*args).numpy(), k_ref, rtol=1e-8, atol=1e-12 * np.max(np.abs(k_ref))
    )


def test_float32_vs_lenstronomy(rng):
    from lenstronomy.LensModel.Profiles.tnfw import TNFW

    x, y, cx, cy = _grid(rng, 0.2)
    ax_ref, _ = TNFW().derivatives(x, y, 0.2, 0.01, 0.6, cx, cy)
    t = lambda v: torch.as_tensor(v, dtype=torch.float32)  # noqa: E731
    ax, _ = tnfw.tnfw_deflection(t(x), t(y), t(0.2), t(0.01), t(0.6), cx, cy)
    np.testing.assert_allclose(ax.double().numpy(), ax_ref, rtol=2e-5, atol=1e-6 * 0.01)
