"""Pair kernels of subslope.physics.pairs.sums against the reference profile functions.

NFW / tNFW (``nfw_pair``, ``tnfw_pair``) against :mod:`subslope.physics.profiles.nfw` and
:mod:`subslope.physics.profiles.tnfw` over x = R/r_s in [1e-8, 1e4] (centre, x ~ 1 and the
branch switches included) and tau = r_t/r_s in [1e-3, 1e3] (the CDM scenes have
tau ~ 2e-3 ... 60: ``subhalos.nfw_parameters`` with r_sub floored at 1e-3 arcsec), in
float64 and float32 (float32 inputs rounded first, the reference evaluated in float64 at
the same rounded points), both broadcast layouts, padded members; EPL (``epl_pair``)
against :func:`subslope.physics.profiles.epl.epl_deflection_and_convergence`; ``split_weight``
and the far/near partition. One compiled graph (NFW ``direct_sums``, float32) runs by
default; the tNFW one (~35 s cold compile) is marked slow.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from subslope.physics.pairs import epl as pair_epl
from subslope.physics.pairs import nfw as nfw_pairs
from subslope.physics.pairs import sums as pk
from subslope.physics.profiles.epl import epl_deflection_and_convergence
from subslope.physics.profiles.nfw import nfw_convergence, nfw_deflection
from subslope.physics.profiles.tnfw import (
    kappa_asymptotic,
    series_weights,
    tnfw_convergence,
    tnfw_deflection,
)

TAUS = (1e-3, 0.02, 0.5, 1.0, math.e, 10.0, 1e3)
R_S, ALPHA_RS, CX, CY = 0.37, 0.011, 0.0, 0.0  # centre at 0: float32 resolves x down to 1e-8
# measured maxima (this grid and a random sweep of 1.2e6 pairs): float32 NFW 7.6e-7, tNFW
# alpha 1.3e-6, kappa 1.3e-6; float64 alpha 2e-14, kappa 2.2e-12 (the reference's own
# closed form just inside x = 10 max(1, tau); the kernel agrees with the converged
# large-radius series to 4e-15, test_tnfw_float64_kappa_against_series)
BOUNDS = {torch.float32: (1.5e-6, 1.5e-6), torch.float64: (1e-13, 3e-12)}


def _radii() -> torch.Tensor:
    """x = R/r_s: log grid, a dense band around x = 1, the centre and the switches."""
    return torch.cat(
        [
            torch.logspace(-8, 4, 1201, dtype=torch.float64),
            1.0 + torch.linspace(-0.3, 0.3, 241, dtype=torch.float64),
            torch.tensor([0.0, 0.5, 0.55, 1.0, 2.0, 1e-12], dtype=torch.float64),
        ]
    )


def _params(profile: str, tau: float | None, dtype, n_pad: int = 0) -> dict[str, torch.Tensor]:
    """One member at (CX, CY) plus ``n_pad`` padded members (alpha_rs = 0, r_s = r_t = 0)."""
    vals = {"x": CX, "y": CY, "r_s": R_S, "alpha_rs": ALPHA_RS}
    if profile == "tnfw":
        vals["r_t"] = tau * R_S
    return {k: torch.tensor([[v] + [0.0] * n_pad], dtype=dtype) for k, v in vals.items()}


def _points(dtype):
    """Points at distance x r_s from the centre (direction (0.6, 0.8)) in ``dtype``, and the
    same rounded points in float64."""
    x = _radii() * R_S
    px, py = (CX + 0.6 * x).to(dtype), (CY + 0.8 * x).to(dtype)
    return px, py, px.double(), py.double()


def _reference(profile: str, tau, px, py):
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    if profile == "nfw":
        ax, ay = nfw_deflection(px, py, t(R_S), t(ALPHA_RS), CX, CY)
        return ax, ay, nfw_convergence(px, py, t(R_S), t(ALPHA_RS), CX, CY)
    ax, ay = tnfw_deflection(px, py, t(R_S), t(ALPHA_RS), t(tau * R_S), CX, CY)
    return ax, ay, tnfw_convergence(px, py, t(R_S), t(ALPHA_RS), t(tau * R_S), CX, CY)


def _pair(profile: str, table: torch.Tensor, px, py, layout: str):
    """The pair function over all (member, point) pairs, returned as (N, Q) tensors."""
    if layout == "members_last":  # rows (1, 1, N) against points (1, Q, 1)
        rows = [table[:, k, None, :] for k in range(table.shape[1])]
        out = pk.PAIR_FUNCTIONS[profile](px[None, :, None], py[None, :, None], rows)
        return [o[0].T for o in out]
    rows = [table[:, k, :, None] for k in range(table.shape[1])]  # (1, N, 1) against (1, N, Q)
    n = table.shape[2]
    out = pk.PAIR_FUNCTIONS[profile](px.expand(n, -1)[None], py.expand(n, -1)[None], rows)
    return [o[0] for o in out]


CASES = [("nfw", None)] + [("tnfw", t) for t in TAUS]


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("profile, tau", CASES)
def test_against_reference(profile, tau, dtype):
    px, py, px64, py64 = _points(dtype)
    table = pk.member_table(profile, _params(profile, tau, dtype), 0)
    ax, ay, k = (o[0].double() for o in _pair(profile, table, px, py, "members_last"))
    rx, ry, rk = _reference(profile, tau, px64, py64)
    assert all(bool(torch.isfinite(o).all()) for o in (ax, ay, k))
    mag = torch.hypot(rx, ry)
    centre = mag == 0
    assert bool((ax[centre] == 0).all() and (ay[centre] == 0).all())
    err_a = float((torch.hypot(ax - rx, ay - ry) / mag)[~centre].max())
    err_k = float(((k - rk) / rk).abs().max())
    bound_a, bound_k = BOUNDS[dtype]
    assert err_a < bound_a and err_k < bound_k, (err_a, err_k)


def test_tnfw_float64_kappa_against_series():
    """Beyond 3 max(1, tau) the converged large-radius series (40 terms) is the truth."""
    for tau in TAUS:
        m = max(1.0, tau)
        x = torch.logspace(math.log10(3.5 * m), math.log10(1e4 * m), 200, dtype=torch.float64)
        table = pk.member_table("tnfw", _params("tnfw", tau, torch.float64), 0)
        _, _, k = _pair("tnfw", table, CX + x * R_S, CY + 0 * x, "members_last")
        shape = kappa_asymptotic(x * x, torch.full_like(x, tau), series_weights(40))
        truth = ALPHA_RS / (2 * (1 + math.log(0.5)) * R_S) * shape
        assert float((k[0] / truth - 1).abs().max()) < 2e-14


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("profile", ["nfw", "tnfw"])
def test_layouts_and_padding(profile, dtype):
    """Both broadcast layouts give identical values; padded members give exact zeros."""
    px, py, _, _ = _points(dtype)
    for tau in TAUS if profile == "tnfw" else (None,):
        table = pk.member_table(profile, _params(profile, tau, dtype, n_pad=2), 0)
        assert bool(torch.isfinite(table).all())
        assert bool((table[0, pk.AMPLITUDE_ROW[profile], 1:] == 0).all())
        a = _pair(profile, table, px, py, "members_last")
        b = _pair(profile, table, px, py, "points_last")
        for u, v in zip(a, b, strict=True):
            assert torch.equal(u, v)
            assert bool((u[1:] == 0).all())


@pytest.mark.parametrize("profile", ["nfw", pytest.param("tnfw", marks=pytest.mark.slow)])
def test_compiled_direct_sums_match_eager(profile):
    gen = torch.Generator().manual_seed(1)
    n, q, d = 37, 23, torch.float32
    u = lambda *s: torch.rand(*s, generator=gen, dtype=d)  # noqa: E731
    params = {
        "x": 2 * u(1, n) - 1,
        "y": 2 * u(1, n) - 1,
        "r_s": 10 ** (2 * u(1, n) - 2),
        "alpha_rs": 1e-3 * u(1, n) * (u(1, n) > 0.2),
    }
    params["r_t"] = params["r_s"] * 10 ** (4 * u(1, n) - 2)
    table = pk.member_table(profile, params, 0)
    x, y = 2 * u(1, q) - 1, 2 * u(1, q) - 1
    x[0, :3], y[0, :3] = table[0, 0, :3], table[0, 1, :3]  # points exactly at centres
    compiled = torch.compile(pk.direct_sums, dynamic=True, fullgraph=True)
    for got, want in zip(
        compiled(x, y, table, profile), pk.direct_sums(x, y, table, profile), strict=True
    ):
        assert bool(torch.isfinite(got).all())
        torch.testing.assert_close(got, want, rtol=2e-5, atol=1e-7)


@pytest.mark.parametrize("name", sorted(nfw_pairs.POLY_DEFS))
def test_polynomial_fits(name):
    """Each fitted polynomial reproduces its function over its interval (float64 evaluation)."""
    fn, (lo, hi), *_ = nfw_pairs.POLY_DEFS[name]
    t = np.linspace(lo, hi, 4001)
    truth = fn(t)
    for double, bound in ((False, 5e-8), (True, 5e-14)):
        (cn, cd), (hn, hd), coef = nfw_pairs.POLY_COEFFICIENTS[double][name]
        v = (t - cn / cd) * (hn / hd)
        approx = np.polynomial.polynomial.polyval(v, [n / d_ for n, d_ in coef])
        assert np.max(np.abs(approx / truth - 1)) < bound


def test_log_matches_torch():
    for dtype, bound in ((torch.float32, 2e-7), (torch.float64, 4e-16)):
        z = torch.cat(
            [
                torch.logspace(-24, 30, 20001, dtype=torch.float64),
                torch.linspace(0.5, 2.0, 2001, dtype=torch.float64),
            ]
        ).to(dtype)
        got = nfw_pairs.fast_log(z, torch.ones((), dtype=dtype)).double()
        want = torch.log(z.double())
        assert float(((got - want).abs() / want.abs().clamp(min=1.0)).max()) < bound


@pytest.mark.parametrize("n_terms", [8, 14])
def test_epl_pair_against_reference(n_terms):
    gen = torch.Generator().manual_seed(3)
    n, q, d = 24, 300, torch.float64
    u = lambda *s: torch.rand(*s, generator=gen, dtype=d)  # noqa: E731
    e = 0.28 * u(1, n).sqrt()
    phi = 2 * math.pi * u(1, n)
    params = {
        "amp": 0.5 * u(1, n) + 0.01,
        "gamma": 1.01 + 1.98 * u(1, n),
        "e1": e * torch.cos(phi),
        "e2": e * torch.sin(phi),
        "x": 2 * u(1, n) - 1,
        "y": 2 * u(1, n) - 1,
    }
    params["gamma"][0, :2] = torch.tensor([1.01, 2.99], dtype=d)
    table = pk.member_table("epl", params, n_terms)
    x, y = 3 * u(1, q) - 1.5, 3 * u(1, q) - 1.5
    rows = [table[:, k, None, :] for k in range(table.shape[1])]
    got = pair_epl.epl_pair(x[:, :, None], y[:, :, None], rows)
    p = {k: v[:, None, :] for k, v in params.items()}
    want = epl_deflection_and_convergence(
        x[:, :, None],
        y[:, :, None],
        p["amp"],
        p["gamma"],
        p["e1"],
        p["e2"],
        p["x"],
        p["y"],
        n_terms=n_terms,
    )
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-12, atol=0)


def test_split_weight():
    r_c = 0.3
    r = torch.linspace(0, 2 * r_c, 2001, dtype=torch.float64)
    w = pk.split_weight(r * 0.6, r * 0.8, 1.0 / r_c**2)
    assert float(w[0]) == 0.0
    # 1 to the last bits from r_c on (r = r_c itself may come out an ulp short of 1 where
    # the CPU fuses the multiply-adds of the radius)
    torch.testing.assert_close(w[r >= r_c], torch.ones_like(w[r >= r_c]), rtol=0, atol=1e-13)
    assert bool((w[r > r_c * (1 + 1e-12)] == 1.0).all())
    assert bool((torch.diff(w) >= 0).all())
    assert bool(((w >= 0) & (w <= 1)).all())


@pytest.mark.parametrize("profile", ["epl", "nfw", "tnfw"])
def test_far_plus_near_equals_direct(profile):
    """W + (1 - W) = 1: far sums plus near sums over all members equal the direct sums."""
    gen = torch.Generator().manual_seed(5)
    n, q, d = 9, 40, torch.float64
    u = lambda *s: torch.rand(*s, generator=gen, dtype=d)  # noqa: E731
    params = {
        "x": 0.4 * u(1, n) - 0.2,
        "y": 0.4 * u(1, n) - 0.2,
        "r_s": 0.05 + 0.2 * u(1, n),
        "alpha_rs": 1e-2 * u(1, n),
        "amp": 0.2 * u(1, n),
        "gamma": 1.5 + u(1, n),
        "e1": 0.2 * u(1, n) - 0.1,
        "e2": 0.2 * u(1, n) - 0.1,
    }
    params["r_t"] = params["r_s"] * (0.1 + 5 * u(1, n))
    table = pk.member_table(profile, params, 14)
    x, y = 0.5 * u(1, q) - 0.25, 0.5 * u(1, q) - 0.25  # within r_c = 0.6 of every member
    inv_rc2 = torch.full((1, n), 1 / 0.6**2, dtype=d)
    far = pk.far_sums(x, y, table, profile, inv_rc2)
    near = pk.near_tile_sums(
        x, y, table[0][:, None, :], profile, inv_rc2, torch.ones(1, n, dtype=d)
    )
    direct = pk.direct_sums(x, y, table, profile)
    for f_, n_, d_ in zip(far, near, direct, strict=True):
        torch.testing.assert_close(f_ + n_, d_, rtol=1e-12, atol=1e-15)
