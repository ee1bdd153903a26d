"""NFW and truncated-NFW (BMO09) lensing: physics identities and numerical stability.

Measured float32-vs-float64 agreement (x = R/R_s in [1e-6, 1e5], tau in {1e-3 .. 1e4};
``OMP_NUM_THREADS=1 .venv/bin/python -m pytest tests/test_nfw.py -q -k float32``) is
recorded in the bounds of ``test_float32_matches_float64`` and in docs/physics.md (NFW).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate

from subslope.physics.profiles import nfw, tnfw

TAUS = [1e-3, 1e-1, 1.0, 10.0, 1e4]
G1 = 1.0 + math.log(0.5)


def _rho_hat(r, tau=None):
    """Dimensionless 3-D density rho/rho_0 at r/R_s (NFW, times BMO09 truncation)."""
    out = 1.0 / (r * (1.0 + r) ** 2)
    return out if tau is None else out * tau**2 / (tau**2 + r**2)


def _breaks(*scales):
    return sorted({s for s in scales if s > 0})


def _kappa_quad(x, tau=None):
    """kappa / (rho_0 R_s) = int rho_hat(sqrt(x^2 + z^2)) dz, by quadrature."""
    f = lambda z: _rho_hat(math.hypot(x, z), tau)  # noqa: E731
    edges = [0.0] + _breaks(x, 1.0, tau or 0.0) + [math.inf]
    return 2.0 * sum(
        integrate.quad(f, a, b, epsabs=0, epsrel=1e-12, limit=200)[0]
        for a, b in zip(edges[:-1], edges[1:])
    )


def _mass2d_quad(x, tau=None):
    """Cylinder mass M_2D(<x) / (rho_0 R_s^3) from the 3-D density (sphere + shell part)."""
    inner = integrate.quad(
        lambda r: 4 * math.pi * r**2 * _rho_hat(r, tau), 0, x, epsabs=0, epsrel=1e-12, limit=200
    )[0]
    shell = lambda r: 4 * math.pi * r**2 * _rho_hat(r, tau) * (1 - math.sqrt(1 - (x / r) ** 2))  # noqa: E731
    edges = [x] + [b for b in _breaks(1.0, tau or 0.0, 10 * x) if b > x] + [math.inf]
    outer = sum(
        integrate.quad(shell, a, b, epsabs=0, epsrel=1e-12, limit=200)[0]
        for a, b in zip(edges[:-1], edges[1:])
    )
    return inner + outer


def _profile(kind, tau):
    """(kappa, deflection) callables with r_s, alpha_rs, r_trunc bound (r_s = 0.7")."""
    r_s, alpha_rs = 0.7, 0.3

    def kappa(x, y):
        t = lambda v: torch.as_tensor(v, dtype=x.dtype)  # noqa: E731
        if kind == "nfw":
            return nfw.nfw_convergence(x, y, t(r_s), t(alpha_rs), 0.0, 0.0)
        return tnfw.tnfw_convergence(x, y, t(r_s), t(alpha_rs), t(tau * r_s), 0.0, 0.0)

    def alpha(x, y):
        t = lambda v: torch.as_tensor(v, dtype=x.dtype)  # noqa: E731
        if kind == "nfw":
            return nfw.nfw_deflection(x, y, t(r_s), t(alpha_rs), 0.0, 0.0)
        return tnfw.tnfw_deflection(x, y, t(r_s), t(alpha_rs), t(tau * r_s), 0.0, 0.0)

    rho0 = alpha_rs / (4 * r_s**2 * G1)
    return kappa, alpha, r_s, rho0


CASES = [("nfw", None)] + [("tnfw", t) for t in (1e-3, 0.1, 1.0, 10.0)]


@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
@pytest.mark.parametrize("kind, tau", CASES)
def test_against_3d_density_quadrature(kind, tau):
    """kappa = projected rho and alpha R pi = M_2D(<R), both from the 3-D density."""
    kappa, alpha, r_s, rho0 = _profile(kind, tau)
    xs = [1e-3, 0.3, 1.0, 2.5, 40.0]
    R = torch.tensor(xs, dtype=torch.float64) * r_s
    k = kappa(R, torch.zeros_like(R)).numpy()
    ax, ay = alpha(R, torch.zeros_like(R))
    assert torch.all(ay == 0)
    for i, x in enumerate(xs):
        k_ref = rho0 * r_s * _kappa_quad(x, tau)
        m_ref = rho0 * r_s**3 * _mass2d_quad(x, tau)
        assert k[i] == pytest.approx(k_ref, rel=1e-9), (x, "kappa")
        assert float(ax[i]) * float(R[i]) * math.pi == pytest.approx(m_ref, rel=1e-9), (x, "mass")


@pytest.mark.parametrize("kind, tau", CASES + [("tnfw", 1e4)])
def test_divergence_and_curl_by_finite_differences(kind, tau, rng):
    kappa, alpha, r_s, _ = _profile(kind, tau)
    pts = rng.uniform(-1, 1, size=(2, 40)) * np.geomspace(0.03, 5, 40) * r_s
    # include points on x = 1 and across the series band edges
    ring = np.array([1.0, 1 - 1e-6, math.sqrt(0.9), math.sqrt(1.1), 2.0]) * r_s
    x = torch.tensor(np.concatenate([pts[0], ring * 0.6]), dtype=torch.float64)
    y = torch.tensor(np.concatenate([pts[1], ring * 0.8]), dtype=torch.float64)
    h = 1e-5 * torch.sqrt(x**2 + y**2)
    axp, ayp = alpha(x + h, y)
    axm, aym = alpha(x - h, y)
    bxp, byp = alpha(x, y + h)
    bxm, bym = alpha(x, y - h)
    div = (axp - axm) / (2 * h) + (byp - bym) / (2 * h)
    curl = (ayp - aym) / (2 * h) - (bxp - bxm) / (2 * h)
    two_k = 2 * kappa(x, y)
    scale = torch.abs(two_k) + torch.abs((axp - axm) / (2 * h))
    assert torch.max(torch.abs(div - two_k) / scale) < 1e-6
    assert torch.max(torch.abs(curl) / scale) < 1e-6


def test_nfw_potential_gradient_is_deflection():
    x = torch.linspace(0.02, 3.0, 25, dtype=torch.float64)
    y = 0.5 * x
    args = (
        torch.tensor(0.4, dtype=torch.float64),
        torch.tensor(0.2, dtype=torch.float64),
        0.0,
        0.0,
    )
    h = 1e-6
    ax, ay = nfw.nfw_deflection(x, y, *args)
    dpx = (nfw.nfw_potential(x + h, y, *args) - nfw.nfw_potential(x - h, y, *args)) / (2 * h)
    dpy = (nfw.nfw_potential(x, y + h, *args) - nfw.nfw_potential(x, y - h, *args)) / (2 * h)
    torch.testing.assert_close(dpx, ax, rtol=1e-7, atol=1e-12)
    torch.testing.assert_close(dpy, ay, rtol=1e-7, atol=1e-12)
    assert float(
        nfw.nfw_potential(
            torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64), *args
        )
    ) == pytest.approx(0.0, abs=1e-20)


def test_nfw_normalisation_and_known_values():
    r_s = torch.tensor(0.5, dtype=torch.float64)
    a_rs = torch.tensor(0.1, dtype=torch.float64)
    ax, ay = nfw.nfw_deflection(r_s * 0.6, r_s * 0.8, r_s, a_rs, 0.0, 0.0)
    assert float(torch.hypot(ax, ay)) == pytest.approx(0.1, rel=1e-14)  # |alpha|(R_s) = alpha_Rs
    k1 = nfw.nfw_convergence(r_s, 0.0, r_s, a_rs, 0.0, 0.0)
    assert float(k1) == pytest.approx(0.1 / (2 * G1 * 0.5) / 3, rel=1e-14)  # f(1) = 1/3


@pytest.mark.parametrize("tau", [1e3, 1e4])
def test_tnfw_tends_to_nfw(tau):
    """|tNFW/NFW - 1| <= 10 (1 + x)^2 / tau^2 for 1e-6 <= x <= 10.

    The truncation effect falls as 1/tau^2 (measured at tau = 1e4: kappa 6e-9 at
    x = 1e-6, 8e-8 at x = 1, 8.5e-6 at x = 10; alpha 5.9e-9, 2.2e-6)."""
    r_s, a_rs = torch.tensor(0.3, dtype=torch.float64), torch.tensor(0.05, dtype=torch.float64)
    X = torch.logspace(-6, 1, 60, dtype=torch.float64)
    R = X * r_s
    tol = 10 * (1 + X) ** 2 / tau**2
    args = (r_s, a_rs)
    k_n = nfw.nfw_convergence(R, 0 * R, *args, 0.0, 0.0)
    k_t = tnfw.tnfw_convergence(R, 0 * R, *args, tau * r_s, 0.0, 0.0)
    a_n = nfw.nfw_deflection(R, 0 * R, *args, 0.0, 0.0)[0]
    a_t = tnfw.tnfw_deflection(R, 0 * R, *args, tau * r_s, 0.0, 0.0)[0]
    assert torch.all(torch.abs(k_t / k_n - 1) < tol)
    assert torch.all(torch.abs(a_t / a_n - 1) < tol)


SPECIAL_X = [0.0, 1e-12, 1e-6, 1 - 1e-6, 1.0, 1 + 1e-6, 1e6]


@pytest.mark.parametrize("tau", [None] + TAUS)
def test_finite_and_continuous_at_special_points(tau, dtype):
    r_s = torch.tensor(0.2, dtype=dtype)
    a_rs = torch.tensor(0.02, dtype=dtype)
    R = torch.tensor(SPECIAL_X, dtype=dtype) * r_s
    zero = torch.zeros_like(R)
    if tau is None:
        k = nfw.nfw_convergence(R, zero, r_s, a_rs, 0.0, 0.0)
        ax, ay = nfw.nfw_deflection(R, zero, r_s, a_rs, 0.0, 0.0)
        psi = nfw.nfw_potential(R, zero, r_s, a_rs, 0.0, 0.0)
        assert torch.isfinite(psi).all()
    else:
        rt = torch.tensor(tau, dtype=dtype) * r_s
        k = tnfw.tnfw_convergence(R, zero, r_s, a_rs, rt, 0.0, 0.0)
        ax, ay = tnfw.tnfw_deflection(R, zero, r_s, a_rs, rt, 0.0, 0.0)
    assert k.dtype == dtype and ax.dtype == dtype
    assert torch.isfinite(k).all() and torch.isfinite(ax).all() and torch.isfinite(ay).all()
    assert torch.all(k > 0) and torch.all(ax[1:] > 0) and ax[0] == 0
    # continuity across x = 1: the three values agree to ~1e-6 relative (slope x 1e-6)
    for q in (k, ax):
        mid = q[3:6].double()
        assert torch.max(torch.abs(mid / mid[1] - 1)) < 1e-5


@pytest.mark.parametrize("tau", [None, 1e-3, 1.0, 1e4])
def test_continuity_across_branch_switches(tau):
    """Series band edges (u = +-0.1), the x = 2 switch of J and the kappa expansion switch."""
    d = torch.float64
    xs = [math.sqrt(0.9), math.sqrt(1.1), 2.0]
    if tau is not None:
        xs += [tnfw.X_ASYMP[d] * max(1.0, tau)]
    for x0 in xs:
        R = torch.tensor([x0 * (1 - 1e-12), x0 * (1 + 1e-12)], dtype=d)
        if tau is None:
            k = nfw.nfw_convergence(R, 0 * R, 1.0, 1.0, 0.0, 0.0)
            a = nfw.nfw_deflection(R, 0 * R, 1.0, 1.0, 0.0, 0.0)[0]
        else:
            k = tnfw.tnfw_convergence(R, 0 * R, 1.0, 1.0, tau, 0.0, 0.0)
            a = tnfw.tnfw_deflection(R, 0 * R, 1.0, 1.0, tau, 0.0, 0.0)[0]
        assert abs(float(k[1] / k[0]) - 1) < 1e-11, (x0, "kappa")
        assert abs(float(a[1] / a[0]) - 1) < 1e-11, (x0, "alpha")


# measured (see module docstring): nfw kappa 2.1e-6, alpha 4.9e-7; tnfw kappa 1.6e-5, alpha 1.7e-6
F32_BOUNDS = {"nfw": (4e-6, 1e-6), "tnfw": (3e-5, 3e-6)}


@pytest.mark.parametrize("kind", ["nfw", "tnfw"])
def test_float32_matches_float64(kind):
    x64 = torch.logspace(-6, 5, 400, dtype=torch.float64)
    x64 = torch.cat([x64, 1 + torch.linspace(-0.2, 0.2, 81, dtype=torch.float64)])
    x32 = x64.float()
    x64 = x32.double()  # same input points in both precisions
    worst_k = worst_a = 0.0
    for tau in TAUS if kind == "tnfw" else [None]:
        out = {}
        for xx in (x32, x64):
            one = torch.ones((), dtype=xx.dtype)
            if kind == "nfw":
                out[xx.dtype] = (
                    nfw.nfw_convergence(xx, 0 * xx, one, one, 0.0, 0.0),
                    nfw.nfw_deflection(xx, 0 * xx, one, one, 0.0, 0.0)[0],
                )
            else:
                t = one * tau
                out[xx.dtype] = (
                    tnfw.tnfw_convergence(xx, 0 * xx, one, one, t, 0.0, 0.0),
                    tnfw.tnfw_deflection(xx, 0 * xx, one, one, t, 0.0, 0.0)[0],
                )
        k32, a32 = out[torch.float32]
        k64, a64 = out[torch.float64]
        worst_k = max(worst_k, float(torch.max(torch.abs(k32.double() / k64 - 1))))
        worst_a = max(worst_a, float(torch.max(torch.abs(a32.double() / a64 - 1))))
    print(f"{kind}: float32 max rel err kappa {worst_k:.2e}, alpha {worst_a:.2e}")
    bound_k, bound_a = F32_BOUNDS[kind]
    assert worst_k < bound_k and worst_a < bound_a


def test_broadcasting_batched_population():
    B, N, P = 2, 3, 50
    d = torch.float64
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(B, 1, P, generator=gen, dtype=d) * 4 - 2
    y = torch.rand(B, 1, P, generator=gen, dtype=d) * 4 - 2
    r_s = torch.rand(B, N, 1, generator=gen, dtype=d) * 0.3 + 0.05
    a_rs = torch.rand(B, N, 1, generator=gen, dtype=d) * 1e-2
    rt = r_s * torch.tensor([0.5, 3.0, 20.0], dtype=d).view(1, N, 1)
    cx = torch.rand(B, N, 1, generator=gen, dtype=d) - 0.5
    cy = torch.rand(B, N, 1, generator=gen, dtype=d) - 0.5
    ax, ay = tnfw.tnfw_deflection(x, y, r_s, a_rs, rt, cx, cy)
    k = nfw.nfw_convergence(x, y, r_s, a_rs, cx, cy)
    assert ax.shape == ay.shape == k.shape == (B, N, P)
    # element (1, 2, 7) equals the scalar evaluation
    s = (1, 2, 7)
    ax1, _ = tnfw.tnfw_deflection(
        x[1, 0, 7], y[1, 0, 7], r_s[1, 2, 0], a_rs[1, 2, 0], rt[1, 2, 0], cx[1, 2, 0], cy[1, 2, 0]
    )
    assert float(ax[s]) == pytest.approx(float(ax1), rel=1e-14)


@pytest.mark.parametrize("kind", ["nfw", "tnfw"])
def test_autograd_is_finite_at_centre_and_x_equal_one(kind):
    d = torch.float64
    x = torch.tensor([0.0, 0.3, 1e-13], dtype=d, requires_grad=True)
    y = torch.tensor([0.0, 0.4, 0.0], dtype=d)
    r_s = torch.tensor(0.5, dtype=d, requires_grad=True)
    a_rs = torch.tensor(0.1, dtype=d)
    if kind == "nfw":
        ax, ay = nfw.nfw_deflection(x, y, r_s, a_rs, 0.0, 0.0)
        k = nfw.nfw_convergence(x, y, r_s, a_rs, 0.0, 0.0)
    else:
        ax, ay = tnfw.tnfw_deflection(x, y, r_s, a_rs, 2 * r_s, 0.0, 0.0)
        k = tnfw.tnfw_convergence(x, y, r_s, a_rs, 2 * r_s, 0.0, 0.0)
    (ax.sum() + ay.sum() + k.sum()).backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(r_s.grad).all()


def test_physical_wrapper_matches_conversion():
    from subslope.physics.cosmology import nfw_params_from_m200_c

    x = torch.zeros(1, 1, 4, dtype=torch.float32)
    m = np.array([[[1e8], [1e9]]])
    c = np.array([[[20.0], [15.0]]])
    r_s, a_rs = nfw.nfw_params_physical(m, c, 0.2, 0.6, like=x)
    assert r_s.dtype == torch.float32 and r_s.shape == (1, 2, 1)
    rs_np, ars_np = nfw_params_from_m200_c(m, c, 0.2, 0.6)
    xx = torch.tensor(rs_np[0, :, 0], dtype=torch.float64).view(1, 2, 1) * torch.ones(
        1, 1, 4, dtype=torch.float64
    )
    ax, _ = nfw.nfw_deflection_physical(xx, 0 * xx, m, c, 0.0, 0.0, 0.2, 0.6)
    np.testing.assert_allclose(ax[0, :, 0].numpy(), ars_np[0, :, 0], rtol=1e-12)


@pytest.mark.gpu
def test_cuda_matches_cpu():
    x = torch.linspace(-2, 2, 1000, dtype=torch.float32).view(1, 1, -1)
    r_s = torch.tensor([0.1, 0.3], dtype=torch.float32).view(1, 2, 1)
    a_rs = torch.tensor([1e-3, 1e-2], dtype=torch.float32).view(1, 2, 1)
    rt = 5 * r_s
    cpu = tnfw.tnfw_deflection(x, 0.3 * x, r_s, a_rs, rt, 0.01, 0.0)[0]
    gpu = tnfw.tnfw_deflection(
        x.cuda(), 0.3 * x.cuda(), r_s.cuda(), a_rs.cuda(), rt.cuda(), 0.01, 0.0
    )[0]
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-5, atol=1e-9)
    k = nfw.nfw_convergence(x.cuda(), 0.3 * x.cuda(), r_s.cuda(), a_rs.cuda(), 0.01, 0.0)
    torch.testing.assert_close(
        k.cpu(), nfw.nfw_convergence(x, 0.3 * x, r_s, a_rs, 0.01, 0.0), rtol=1e-5, atol=1e-9
    )
