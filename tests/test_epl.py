"""Physics tests of the EPL profile (subslope.physics.profiles.epl) and the ellipse helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from lensing_checks import fd_grad, ring_points
from scipy.special import hyp2f1

from subslope.physics.profiles.ellipse import (
    ellipse_frame,
    ellipticity_to_q_phi,
    from_frame,
    q_phi_to_ellipticity,
    to_frame,
)
from subslope.physics.profiles.epl import (
    N_TERMS_DEFAULT,
    amp_to_theta_e,
    epl_convergence,
    epl_convergence_theta_e,
    epl_deflection,
    epl_deflection_theta_e,
    epl_potential,
    theta_e_to_amp,
)

F64 = torch.float64

# (theta_E, gamma, e1, e2, cx, cy): round/elliptical, rotated, off-centre, stiff slopes.
CASES = [
    (1.0, 2.0, 0.0, 0.0, 0.0, 0.0),
    (1.1, 1.01, 0.15, -0.1, 0.1, -0.2),
    (0.8, 1.5, -0.2, 0.2, -0.3, 0.05),
    (1.2, 2.0, 0.2, 0.0, 0.0, 0.1),
    (0.9, 2.5, 0.05, 0.19, 0.2, 0.2),
    (1.3, 2.99, -0.2, -0.2, -0.1, 0.0),
]


# ---------------------------------------------------------------- ellipse helpers
def test_ellipse_roundtrip_and_round_case(rng):
    q = torch.tensor(rng.uniform(0.5, 1.0, 50))
    phi = torch.tensor(rng.uniform(-np.pi / 2 + 1e-6, np.pi / 2, 50))
    e1, e2 = q_phi_to_ellipticity(q, phi)
    q2, phi2 = ellipticity_to_q_phi(e1, e2)
    torch.testing.assert_close(q2, q, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(phi2, phi, rtol=0, atol=1e-9)
    qf, c, s = ellipse_frame(e1, e2)
    torch.testing.assert_close(c, torch.cos(phi), rtol=0, atol=1e-12)
    torch.testing.assert_close(s, torch.sin(phi), rtol=0, atol=1e-12)
    # exactly round: q = 1, no rotation, finite gradients
    z = torch.zeros(3, dtype=F64, requires_grad=True)
    qf, c, s = ellipse_frame(z, z)
    assert torch.equal(qf.detach(), torch.ones(3, dtype=F64)) and torch.equal(
        s.detach(), torch.zeros(3, dtype=F64)
    )
    (qf.sum() + c.sum() + s.sum()).backward()
    assert torch.isfinite(z.grad).all()
    # rotation helpers are inverse of each other
    x, y = torch.tensor([0.3, -1.0], dtype=F64), torch.tensor([0.7, 0.2], dtype=F64)
    xr, yr = to_frame(x, y, c[:2], s[:2] + 0.0)
    xb, yb = from_frame(
        *to_frame(x, y, torch.cos(phi[:2]), torch.sin(phi[:2])),
        torch.cos(phi[:2]),
        torch.sin(phi[:2]),
    )
    torch.testing.assert_close(xb, x)
    torch.testing.assert_close(yb, y)


# ---------------------------------------------------------------- differential identities
@pytest.mark.parametrize("theta_e,gamma,e1,e2,cx,cy", CASES)
def test_divergence_is_twice_kappa_and_curl_free(theta_e, gamma, e1, e2, cx, cy, rng):
    x, y = ring_points(rng, lo=0.3)
    x, y = x + cx, y + cy
    amp = theta_e ** (gamma - 1)
    f = lambda xx, yy: epl_deflection(xx, yy, amp, gamma, e1, e2, cx, cy, n_terms=40)
    dfx, dfy = fd_grad(f, x, y)
    div = dfx[0] + dfy[1]
    curl = dfx[1] - dfy[0]
    kappa = epl_convergence(x, y, amp, gamma, e1, e2, cx, cy)
    torch.testing.assert_close(div, 2 * kappa, rtol=1e-7, atol=1e-10)
    assert curl.abs().max() < 1e-7 * kappa.abs().max()
    # potential: grad psi = alpha
    p = lambda xx, yy: (epl_potential(xx, yy, amp, gamma, e1, e2, cx, cy, n_terms=40),)
    ax, ay = f(x, y)
    px, py = fd_grad(p, x, y)
    torch.testing.assert_close(px[0], ax, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(py[0], ay, rtol=1e-8, atol=1e-10)


def test_kappa_formula_lenstronomy_convention():
    """kappa = (3-g)/2 (theta_E / sqrt(q x'^2 + y'^2/q))^(g-1), x' rotated by phi."""
    q, phi, te, g = 0.7, 0.4, 1.2, 1.8
    e1, e2 = [
        float(v)
        for v in q_phi_to_ellipticity(torch.tensor(q, dtype=F64), torch.tensor(phi, dtype=F64))
    ]
    x, y = torch.tensor([0.5, -1.1, 0.0], dtype=F64), torch.tensor([0.3, 0.4, -0.9], dtype=F64)
    xp = math.cos(phi) * (x - 0.1) + math.sin(phi) * (y + 0.2)
    yp = -math.sin(phi) * (x - 0.1) + math.cos(phi) * (y + 0.2)
    expect = (3 - g) / 2 * (te / torch.sqrt(q * xp**2 + yp**2 / q)) ** (g - 1)
    got = epl_convergence_theta_e(x, y, te, g, e1, e2, 0.1, -0.2)
    torch.testing.assert_close(got, expect, rtol=1e-12, atol=0)


# ---------------------------------------------------------------- closed forms
def test_sis_limit():
    x, y = torch.tensor([0.3, -1.7, 2.0], dtype=F64), torch.tensor([0.4, 0.1, -2.0], dtype=F64)
    ax, ay = epl_deflection_theta_e(x, y, 1.3, 2.0, 0.0, 0.0)
    r = torch.hypot(x, y)
    torch.testing.assert_close(ax, 1.3 * x / r, rtol=1e-14, atol=0)
    torch.testing.assert_close(ay, 1.3 * y / r, rtol=1e-14, atol=0)


@pytest.mark.parametrize("gamma", [1.01, 1.3, 1.7, 2.0, 2.4, 2.99])
def test_round_closed_form(gamma, dtype):
    r = torch.tensor([1e-3, 0.04, 0.5, 1.0, 3.0], dtype=dtype)
    th = torch.tensor([0.1, 2.0, -1.0, 3.0, -2.5], dtype=dtype)
    amp = 3e-2
    ax, ay = epl_deflection(r * torch.cos(th), r * torch.sin(th), amp, gamma, 0.0, 0.0)
    torch.testing.assert_close(torch.hypot(ax, ay), amp * r ** (2 - gamma), rtol=5e-6, atol=0)
    k = epl_convergence(r * torch.cos(th), r * torch.sin(th), amp, gamma, 0.0, 0.0)
    torch.testing.assert_close(k, (3 - gamma) / 2 * amp * r ** (1 - gamma), rtol=5e-6, atol=0)


@pytest.mark.parametrize(
    "gamma,kappa1,alpha1",
    [
        (1.01, 1.02e-2, 1.03e-2),
        (1.5, 3.26e-4, 4.34e-4),
        (2.0, 2.13e-4, 4.26e-4),
        (2.9, 3.41e-5, 6.81e-4),
    ],
)
def test_science_reference_values(gamma, kappa1, alpha1, dtype):
    """docs/simulation.md (M200 = 1e8 Msun, round): kappa(1") listed => alpha(1") listed (3
    digits)."""
    one = torch.ones(1, dtype=dtype)
    k_unit = epl_convergence(one, 0 * one, 1.0, gamma, 0.0, 0.0)  # kappa(1") per unit amplitude
    amp = kappa1 / k_unit
    ax, ay = epl_deflection(one, 0 * one, amp, gamma, 0.0, 0.0)
    # both numbers are rounded to 3 digits: allow half a unit of the last digit of each
    mant = lambda v: v / 10 ** math.floor(math.log10(v))
    assert abs(ax.item() / alpha1 - 1) < 0.5e-2 / mant(kappa1) + 0.5e-2 / mant(alpha1) + 1e-6
    assert abs(ay.item()) < 1e-12


def test_mass_inside_critical_ellipse():
    """Gauss: flux of alpha through q x'^2 + y'^2/q = theta_E^2 equals 2 pi theta_E^2 (mean kappa
    1)."""
    te, n = 1.1, 4096
    s = torch.linspace(0, 2 * math.pi, n + 1, dtype=F64)[:-1]
    for g, e1, e2 in [
        (1.01, 0.2, -0.1),
        (1.5, -0.15, 0.2),
        (2.0, 0.2, 0.2),
        (2.7, 0.05, -0.2),
        (2.99, 0.0, 0.0),
    ]:
        q, c, sn = (
            v.item()
            for v in ellipse_frame(torch.tensor(e1, dtype=F64), torch.tensor(e2, dtype=F64))
        )
        xp, yp = te / math.sqrt(q) * torch.cos(s), te * math.sqrt(q) * torch.sin(s)
        nxp, nyp = (
            te * math.sqrt(q) * torch.cos(s),
            te / math.sqrt(q) * torch.sin(s),
        )  # outward n dl/ds
        x, y = c * xp - sn * yp + 0.1, sn * xp + c * yp - 0.2
        nx, ny = c * nxp - sn * nyp, sn * nxp + c * nyp
        ax, ay = epl_deflection_theta_e(x, y, te, g, e1, e2, 0.1, -0.2)
        flux = ((ax * nx + ay * ny).sum() * (2 * math.pi / n)).item()
        assert abs(flux / (2 * math.pi * te**2) - 1) < 1e-10, (g, e1, e2, flux)


# ---------------------------------------------------------------- series accuracy
def test_series_matches_scipy_hyp2f1(rng):
    """Independent check of the series with scipy's 2F1 (TM15 eq. 13) at the prior edges."""
    x, y = ring_points(rng, 300, 0.05, 3.0)
    for g, e1, e2 in [(1.01, 0.2, 0.2), (1.9, -0.2, 0.2), (2.99, -0.2, -0.2), (2.3, 0.13, 0.0)]:
        q, c, s = (
            v.item()
            for v in ellipse_frame(torch.tensor(e1, dtype=F64), torch.tensor(e2, dtype=F64))
        )
        t = g - 1
        xp, yp = (c * x + s * y).numpy(), (-s * x + c * y).numpy()
        Z = q * xp + 1j * yp
        R = np.abs(Z)
        a = (
            2
            / (1 + q)
            * q ** (t / 2)
            * R ** (-t)
            * Z
            * hyp2f1(1, t / 2, 2 - t / 2, -(1 - q) / (1 + q) * Z / Z.conj())
        )
        ax, ay = (c * a.real - s * a.imag), (s * a.real + c * a.imag)
        bx, by = epl_deflection(x, y, 1.0, g, e1, e2)
        err = np.hypot(bx.numpy() - ax, by.numpy() - ay) / np.abs(a)
        assert err.max() < 5e-8, (g, e1, e2, err.max())


def test_default_truncation_error_bound(rng):
    """Default n_terms vs a converged (60-term) float64 sum: <= 5e-8 relative over the prior."""
    n = 400
    x, y = ring_points(rng, 500, 0.01, 3.0)
    g = torch.tensor(rng.uniform(1.01, 2.99, (n, 1)))
    e1 = torch.tensor(rng.uniform(-0.2, 0.2, (n, 1)))
    e2 = torch.tensor(rng.uniform(-0.2, 0.2, (n, 1)))
    # include the worst corner explicitly
    g[0], e1[0], e2[0] = 2.99, 0.2, 0.2
    ax, ay = epl_deflection(x, y, 1.0, g, e1, e2)
    bx, by = epl_deflection(x, y, 1.0, g, e1, e2, n_terms=60)
    err = (torch.hypot(ax - bx, ay - by) / torch.hypot(bx, by)).max().item()
    assert N_TERMS_DEFAULT == 14
    assert err < 5e-8, err


def test_float32_vs_float64(rng):
    """float32 vs float64 (docs/physics.md (EPL)): on identical (f32-representable) inputs
    <= 2e-6 relative (measured 5.6e-7); end to end, including the rounding of the inputs
    and the cancellation in x - cx near the centre, <= 2e-5 (measured 6.7e-6)."""
    x, y = ring_points(rng, 500, 0.02, 2.5)
    m = 64
    g = torch.tensor(rng.uniform(1.01, 2.99, (m, 1)))
    e1 = torch.tensor(rng.uniform(-0.2, 0.2, (m, 1)))
    e2 = torch.tensor(rng.uniform(-0.2, 0.2, (m, 1)))
    cx, cy = (
        torch.tensor(rng.uniform(-0.2, 0.2, (m, 1))),
        torch.tensor(rng.uniform(-0.2, 0.2, (m, 1))),
    )
    amp = torch.tensor(rng.uniform(1e-3, 1.5, (m, 1)))
    args = [amp, g, e1, e2, cx, cy]
    fargs = [a.float() for a in args]
    fx, fy = epl_deflection(x.float(), y.float(), *fargs)
    kf = epl_convergence(x.float(), y.float(), *fargs)
    assert fx.dtype == torch.float32 and kf.dtype == torch.float32
    for (xx, yy, aa), bound in [
        ((x.float().double(), y.float().double(), [a.double() for a in fargs]), 2e-6),
        ((x, y, args), 2e-5),
    ]:
        ax, ay = epl_deflection(xx, yy, *aa)
        k = epl_convergence(xx, yy, *aa)
        err = (torch.hypot(fx.double() - ax, fy.double() - ay) / torch.hypot(ax, ay)).max().item()
        assert err < bound, err
        assert ((kf.double() - k).abs() / k).max().item() < bound


# ---------------------------------------------------------------- limits
def test_continuity_near_round():
    x, y = torch.tensor([0.3, -1.2, 0.9], dtype=F64), torch.tensor([0.8, 0.5, -2.0], dtype=F64)
    q = torch.tensor(1 - 1e-9, dtype=F64)
    e1, e2 = q_phi_to_ellipticity(q, torch.tensor(0.3, dtype=F64))
    for g in (1.01, 2.0, 2.99):
        a0 = torch.stack(epl_deflection(x, y, 0.5, g, 0.0, 0.0))
        a1 = torch.stack(epl_deflection(x, y, 0.5, g, e1, e2))
        a2 = torch.stack(epl_deflection(x, y, 0.5, g, 1e-12, -1e-12))
        assert (a1 - a0).abs().max() < 1e-8 * a0.abs().max()
        assert (a2 - a0).abs().max() < 1e-10 * a0.abs().max()


@pytest.mark.parametrize("gamma", [1.01, 2.99])
def test_no_nan_on_stiff_grid(gamma, dtype):
    pts = torch.tensor([0.0, 1e-12, -1e-12, 1e-9, 1e-6, 0.04, 2.0], dtype=dtype)
    x, y = torch.meshgrid(pts, pts, indexing="ij")
    x, y = x.reshape(1, -1), y.reshape(1, -1)
    amp = theta_e_to_amp(torch.tensor([[1e-7], [1.0], [1e-199]], dtype=F64), gamma).to(dtype)
    for e1, e2 in [(0.0, 0.0), (0.2, -0.2), (-0.2, 0.0)]:
        ax, ay = epl_deflection(x, y, amp, gamma, e1, e2)
        k = epl_convergence(x, y, amp, gamma, e1, e2)
        p = epl_potential(x, y, amp, gamma, e1, e2)
        for v in (ax, ay, k, p):
            assert v.dtype == dtype and v.shape == (3, 49)
            assert torch.isfinite(v).all()
        assert (ax[:, 0] == 0).all() and (ay[:, 0] == 0).all()  # exact centre


def test_tiny_amplitude_gamma_near_one():
    """theta_E ~ 1e-199 arcsec at gamma = 1.01 is carried as amp ~ 1e-2 (docs/simulation.md)."""
    amp = theta_e_to_amp(torch.tensor(1e-199, dtype=F64), 1.01)
    assert 1.0e-2 < amp.item() < 1.1e-2
    assert amp_to_theta_e(amp, 1.01).item() == pytest.approx(1e-199, rel=1e-9)
    assert theta_e_to_amp(torch.tensor(0.0), 1.5).item() == 0.0
    x = torch.tensor([1.0], dtype=torch.float32)
    ax, _ = epl_deflection(x, 0 * x, amp.float(), 1.01, 0.0, 0.0)
    assert ax.item() == pytest.approx(amp.item(), rel=1e-6)


def test_broadcasting_population(dtype):
    B, N, P = 2, 5, 7
    x = torch.rand(B, 1, P, dtype=dtype)
    y = torch.rand(B, 1, P, dtype=dtype)
    par = lambda lo, hi: lo + (hi - lo) * torch.rand(B, N, 1, dtype=dtype)
    amp, g, e1, e2, cx, cy = (
        par(0, 1),
        par(1.01, 2.99),
        par(-0.2, 0.2),
        par(-0.2, 0.2),
        par(-1, 1),
        par(-1, 1),
    )
    ax, ay = epl_deflection(x, y, amp, g, e1, e2, cx, cy)
    assert ax.shape == (B, N, P) and ax.dtype == dtype
    one_x, one_y = epl_deflection(
        x[1, 0], y[1, 0], amp[1, 3], g[1, 3], e1[1, 3], e2[1, 3], cx[1, 3], cy[1, 3]
    )
    torch.testing.assert_close(ax[1, 3], one_x)
    torch.testing.assert_close(ay[1, 3], one_y)
    assert epl_convergence(x, y, amp, g, e1, e2, cx, cy).shape == (B, N, P)


def test_autograd_finite_at_round_and_centre():
    x = torch.tensor([0.0, 0.5], dtype=F64)
    p = torch.tensor([0.3, 1.5, 0.0, 0.0], dtype=F64, requires_grad=True)
    ax, ay = epl_deflection(x, x, p[0], p[1], p[2], p[3])
    (ax.sum() + ay.sum() + epl_convergence(x, x, p[0], p[1], p[2], p[3]).sum()).backward()
    assert torch.isfinite(p.grad).all()


def test_errors_name_argument():
    x = torch.zeros(3)
    with pytest.raises(ValueError, match="gamma"):
        epl_deflection(x, x, 1.0, 3.2, 0.0, 0.0)
    with pytest.raises(ValueError, match="amp"):
        epl_convergence(x, x, -1.0, 2.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="e1, e2"):
        epl_deflection(x, x, 1.0, 2.0, 0.9, 0.9)
    with pytest.raises(ValueError, match="n_terms"):
        epl_deflection(x, x, 1.0, 2.0, 0.0, 0.0, n_terms=0)
    with pytest.raises(ValueError, match="x must"):
        epl_deflection([0.0], x, 1.0, 2.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="theta_e"):
        theta_e_to_amp(torch.tensor(-1.0), 2.0)


@pytest.mark.gpu
def test_cuda_matches_cpu(rng):
    x, y = ring_points(rng, 300, 0.0, 2.0)
    args = (
        torch.tensor([[0.5], [1e-2]]),
        torch.tensor([[2.2], [1.01]]),
        torch.tensor([[0.1], [-0.2]]),
        torch.tensor([[0.0], [0.2]]),
        torch.tensor([[0.1], [0.0]]),
        torch.tensor([[0.0], [-0.3]]),
    )
    ax, ay = epl_deflection(x.float(), y.float(), *args)
    gx, gy = epl_deflection(x.float().cuda(), y.float().cuda(), *(a.cuda() for a in args))
    assert gx.device.type == "cuda"
    torch.testing.assert_close(gx.cpu(), ax, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(gy.cpu(), ay, rtol=1e-5, atol=1e-7)
