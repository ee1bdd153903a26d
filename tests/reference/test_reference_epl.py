"""Cross-check of the mass profiles against lenstronomy (skipped when it is absent).

Tolerances: EPL vs lenstronomy ``EPL`` (scipy hyp2f1, exact): rtol 1e-7 on alpha
(default n_terms = 14; truncation <= 3e-8), 1e-12 on kappa. ``EPL_NUMBA`` (its own
series, tolerance ~1e-8 in lenstronomy): rtol 1e-6. MULTIPOLE, SHEAR: 1e-12.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.physics.profiles.epl import epl_convergence_theta_e, epl_deflection_theta_e
from subslope.physics.profiles.multipole import multipole_convergence, multipole_deflection
from subslope.physics.profiles.shear import shear_deflection

pytestmark = pytest.mark.reference
F64 = torch.float64

EPL_GRID = [
    (te, g, e1, e2, cx, cy)
    for te, cx, cy in [(1.1, 0.1, -0.15), (0.05, -0.4, 0.3)]
    for g in (1.2, 1.6, 2.0, 2.4, 2.8)
    for e1, e2 in [(0.0, 0.0), (0.2, -0.2), (-0.13, 0.07), (0.0, 0.19)]
]


@pytest.fixture(scope="module")
def pts():
    g = np.random.default_rng(7)
    return g.uniform(-2, 2, 400), g.uniform(-2, 2, 400)


def _rel_vec(ax, ay, bx, by):
    return np.max(np.hypot(ax - bx, ay - by) / np.maximum(np.hypot(bx, by), 1e-300))


@pytest.mark.parametrize("te,g,e1,e2,cx,cy", EPL_GRID)
def test_epl_vs_lenstronomy(te, g, e1, e2, cx, cy, pts):
    from lenstronomy.LensModel.Profiles.epl import EPL

    x, y = pts
    ref = EPL()
    bx, by = ref.derivatives(x, y, te, g, e1, e2, cx, cy)
    fxx, _, _, fyy = ref.hessian(x, y, te, g, e1, e2, cx, cy)
    X, Y = torch.tensor(x, dtype=F64), torch.tensor(y, dtype=F64)
    ax, ay = epl_deflection_theta_e(X, Y, torch.tensor(te, dtype=F64), g, e1, e2, cx, cy)
    k = epl_convergence_theta_e(X, Y, torch.tensor(te, dtype=F64), g, e1, e2, cx, cy).numpy()
    assert _rel_vec(ax.numpy(), ay.numpy(), bx, by) < 1e-7
    np.testing.assert_allclose(k, (fxx + fyy) / 2, rtol=1e-9)


@pytest.mark.parametrize("te,g,e1,e2,cx,cy", EPL_GRID[::3])
def test_epl_vs_lenstronomy_numba(te, g, e1, e2, cx, cy, pts):
    pytest.importorskip("numba")
    from lenstronomy.LensModel.Profiles.epl_numba import EPL_numba

    x, y = pts
    bx, by = EPL_numba().derivatives(x, y, te, g, e1, e2, cx, cy)
    X, Y = torch.tensor(x, dtype=F64), torch.tensor(y, dtype=F64)
    ax, ay = epl_deflection_theta_e(X, Y, torch.tensor(te, dtype=F64), g, e1, e2, cx, cy)
    assert _rel_vec(ax.numpy(), ay.numpy(), bx, by) < 1e-6


@pytest.mark.parametrize("m", [3, 4])
@pytest.mark.parametrize("a_m,phi_m,cx,cy", [(0.05, 0.4, 0.0, 0.0), (0.01, -2.9, 0.1, -0.2)])
def test_multipole_vs_lenstronomy(m, a_m, phi_m, cx, cy, pts):
    from lenstronomy.LensModel.Profiles.multipole import Multipole

    x, y = pts
    ref = Multipole()
    bx, by = ref.derivatives(x, y, m, a_m, phi_m, cx, cy)
    fxx, _, _, fyy = ref.hessian(x, y, m, a_m, phi_m, cx, cy)
    X, Y = torch.tensor(x, dtype=F64), torch.tensor(y, dtype=F64)
    ax, ay = multipole_deflection(X, Y, m, a_m, phi_m, cx, cy)
    np.testing.assert_allclose(ax.numpy(), bx, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(ay.numpy(), by, rtol=1e-10, atol=1e-13)
    k = multipole_convergence(X, Y, m, a_m, phi_m, cx, cy).numpy()
    np.testing.assert_allclose(k, (fxx + fyy) / 2, rtol=1e-9, atol=1e-12)


def test_shear_vs_lenstronomy(pts):
    from lenstronomy.LensModel.Profiles.shear import Shear

    x, y = pts
    for g1, g2, x0, y0 in [(0.05, -0.08, 0.0, 0.0), (-0.1, 0.03, 0.2, -0.1)]:
        bx, by = Shear().derivatives(x, y, g1, g2, x0, y0)
        ax, ay = shear_deflection(
            torch.tensor(x, dtype=F64), torch.tensor(y, dtype=F64), g1, g2, x0, y0
        )
        np.testing.assert_allclose(ax.numpy(), bx, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(ay.numpy(), by, rtol=1e-12, atol=1e-15)
