"""Physics tests of the multipole, shear and sheet profiles."""

from __future__ import annotations

import pytest
import torch
from lensing_checks import fd_grad, ring_points

from subslope.physics.profiles.multipole import (
    multipole_convergence,
    multipole_deflection,
    multipole_deflections,
    multipole_potential,
)
from subslope.physics.profiles.shear import shear_convergence, shear_deflection, shear_potential
from subslope.physics.profiles.sheet import sheet_convergence, sheet_deflection, sheet_potential

F64 = torch.float64


def _check_identities(defl, conv, pot, x, y, rtol=1e-8, atol=1e-10, h=1e-3):
    dfx, dfy = fd_grad(defl, x, y, h)
    ax, ay = defl(x, y)
    kappa = conv(x, y)
    torch.testing.assert_close(dfx[0] + dfy[1], 2 * kappa, rtol=rtol, atol=atol)
    torch.testing.assert_close(dfx[1] - dfy[0], torch.zeros_like(kappa), rtol=0, atol=atol)
    px, py = fd_grad(lambda a, b: (pot(a, b),), x, y, h)
    torch.testing.assert_close(px[0], ax, rtol=rtol, atol=atol)
    torch.testing.assert_close(py[0], ay, rtol=rtol, atol=atol)


@pytest.mark.parametrize("m", [2, 3, 4, 5])
@pytest.mark.parametrize("a_m,phi_m,cx,cy", [(0.05, 0.3, 0.0, 0.0), (0.02, -2.5, 0.15, -0.1)])
def test_multipole_identities(m, a_m, phi_m, cx, cy, rng):
    x, y = ring_points(rng, lo=0.2)
    x, y = x + cx, y + cy
    args = (m, a_m, phi_m, cx, cy)
    _check_identities(
        lambda a, b: multipole_deflection(a, b, *args),
        lambda a, b: multipole_convergence(a, b, *args),
        lambda a, b: multipole_potential(a, b, *args),
        x,
        y,
        atol=1e-9,
        h=2e-4,
    )


def test_multipole_closed_form_kappa():
    """kappa = a_m cos(m(theta - phi_m)) / (2 r), the lenstronomy convention
    (docs/simulation.md)."""
    r, th = torch.tensor([0.5, 1.0, 2.0], dtype=F64), torch.tensor([0.2, -1.3, 2.9], dtype=F64)
    for m in (3, 4):
        k = multipole_convergence(r * torch.cos(th), r * torch.sin(th), m, 0.04, 0.7)
        torch.testing.assert_close(k, 0.04 * torch.cos(m * (th - 0.7)) / (2 * r))
        ax, ay = multipole_deflection(r * torch.cos(th), r * torch.sin(th), m, 0.04, 0.7)
        a_r = ax * torch.cos(th) + ay * torch.sin(th)
        torch.testing.assert_close(a_r, 0.04 / (1 - m * m) * torch.cos(m * (th - 0.7)))


def test_multipole_centre_and_dtype(dtype):
    pts = torch.tensor([0.0, 1e-12, -1e-9, 0.04], dtype=dtype)
    x, y = torch.meshgrid(pts, pts, indexing="ij")
    a_m = torch.tensor([[0.05], [0.0]], dtype=dtype)
    for m in (3, 4):
        for f in (multipole_deflection, multipole_convergence, multipole_potential):
            out = f(x.reshape(1, -1), y.reshape(1, -1), m, a_m, torch.zeros_like(a_m))
            for v in out if isinstance(out, tuple) else (out,):
                assert v.dtype == dtype and v.shape == (2, 16) and torch.isfinite(v).all()
    with pytest.raises(ValueError, match="m must"):
        multipole_deflection(x, y, 1, 0.1, 0.0)
    with pytest.raises(ValueError, match="m must"):
        multipole_deflection(x, y, 3.0, 0.1, 0.0)


@pytest.mark.parametrize("g1,g2,x0,y0", [(0.05, -0.08, 0.0, 0.0), (-0.1, 0.1, 0.2, -0.3)])
def test_shear_identities(g1, g2, x0, y0, rng):
    x, y = ring_points(rng, lo=0.0)
    _check_identities(
        lambda a, b: shear_deflection(a, b, g1, g2, x0, y0),
        lambda a, b: shear_convergence(a, b, g1, g2, x0, y0),
        lambda a, b: shear_potential(a, b, g1, g2, x0, y0),
        x,
        y,
    )
    ax, ay = shear_deflection(
        torch.tensor([1.0 + x0], dtype=F64), torch.tensor([y0], dtype=F64), g1, g2, x0, y0
    )
    assert ax.item() == pytest.approx(g1) and ay.item() == pytest.approx(g2)


@pytest.mark.parametrize("kappa0,cx,cy", [(0.1, 0.0, 0.0), (-0.03, 0.2, -0.1)])
def test_sheet_identities(kappa0, cx, cy, rng):
    x, y = ring_points(rng, lo=0.0)
    _check_identities(
        lambda a, b: sheet_deflection(a, b, kappa0, cx, cy),
        lambda a, b: sheet_convergence(a, b, kappa0, cx, cy),
        lambda a, b: sheet_potential(a, b, kappa0, cx, cy),
        x,
        y,
    )


def test_broadcast_population(dtype):
    B, N, P = 2, 3, 5
    x, y = torch.rand(B, 1, P, dtype=dtype), torch.rand(B, 1, P, dtype=dtype)
    k0 = torch.rand(B, N, 1, dtype=dtype)
    assert sheet_deflection(x, y, k0)[0].shape == (B, N, P)
    assert sheet_convergence(x, y, k0).shape == (B, N, P)
    g = torch.rand(B, N, 1, dtype=dtype)
    assert shear_deflection(x, y, g, g)[1].shape == (B, N, P)
    assert shear_convergence(x, y, g, g).shape == (B, N, P)
    assert multipole_deflection(x, y, 4, g, g, g, g)[0].dtype == dtype
    with pytest.raises(ValueError, match="x must"):
        sheet_deflection([1.0], y, 0.1)


@pytest.mark.gpu
def test_cuda_paths():
    x = torch.linspace(-2, 2, 50, device="cuda")
    for out in (
        multipole_deflection(x, x.flip(0), 3, 0.05, 0.3),
        shear_deflection(x, x, 0.1, 0.0),
        sheet_deflection(x, x, -0.02),
    ):
        assert out[0].device.type == "cuda" and torch.isfinite(out[0]).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_multipoles_about_one_centre_equal_each_order_alone(dtype):
    g = torch.Generator().manual_seed(3)
    x, y = (torch.randn(2, 500, generator=g, dtype=dtype) for _ in range(2))
    a3, a4, p3, p4, cx = (0.05 * torch.rand(2, 1, generator=g, dtype=dtype) for _ in range(5))
    both = multipole_deflections(x, y, (3, 4), (a3, a4), (p3, p4), cx, -cx)
    for (ax, ay), (m, a, p) in zip(both, ((3, a3, p3), (4, a4, p4))):
        bx, by = multipole_deflection(x, y, m, a, p, cx, -cx)
        assert torch.equal(ax, bx) and torch.equal(ay, by)
    with pytest.raises(ValueError, match="orders must increase"):
        multipole_deflections(x, y, (4, 3), (a3, a4), (p3, p4))
