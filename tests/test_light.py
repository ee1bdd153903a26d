"""Sérsic and pixelated light profiles."""

import math

import numpy as np
import pytest
import torch
from scipy.special import gammainc

from subslope.physics.grid import bin_supersampled, pixel_grid
from subslope.physics.light import (
    SersicEllipse,
    magnitude_to_flux,
    pad_stamps,
    pixelated_light,
    sersic_amp_from_flux,
    sersic_b_n,
    sersic_ellipse,
    sersic_ellipse_from_magnitude,
    sersic_total_flux,
)
from subslope.physics.light.sersic import e1e2_to_q_phi, elliptical_radius_squared

# ------------------------------------------------------------------------- Sérsic


def _polar_flux(fn, r_s, n_r=3000, n_t=256):
    """∫∫ I r dr dθ on a log-radial polar grid about the centre (float64)."""
    lr = torch.linspace(math.log(1e-7 * r_s), math.log(1e4 * r_s), n_r, dtype=torch.float64)
    th = (torch.arange(n_t, dtype=torch.float64) + 0.5) * (2 * math.pi / n_t)
    r = torch.exp(lr)[:, None]
    img = fn(r * torch.cos(th), r * torch.sin(th))
    radial = img.mean(dim=1) * 2 * math.pi * r[:, 0] ** 2  # dF/dlnr
    return float(torch.trapezoid(radial, lr))


@pytest.mark.parametrize("n", [0.5, 1.0, 2.0, 4.0, 8.0])
def test_sersic_total_flux_matches_magnitude(n):
    mag, r_s, e1, e2 = 18.0, 0.8, 0.25, -0.15  # q ≈ 0.54
    q, _ = e1e2_to_q_phi(torch.tensor(e1), torch.tensor(e2))
    assert float(q) < 0.6
    flux = float(magnitude_to_flux(torch.tensor(mag, dtype=torch.float64)))
    assert flux == pytest.approx(10 ** (-0.4 * (mag - 25.127)), rel=1e-12)
    got = _polar_flux(
        lambda x, y: sersic_ellipse_from_magnitude(x, y, mag, r_s, n, e1, e2, r_floor=0.0), r_s
    )
    # light outside 1e4 R_s (analytic, incomplete gamma) is negligible at this tolerance
    b = float(sersic_b_n(torch.tensor(n, dtype=torch.float64)))
    assert 1.0 - gammainc(2 * n, b * 1e4 ** (1 / n)) < 1e-6
    assert got == pytest.approx(flux, rel=1e-6)  # measured ≤ 2e-8


def test_sersic_flux_independent_of_q_on_pixel_grid():
    """Pixel sum on a supersampled grid (n = 1, light inside the field) vs magnitude."""
    x, y = pixel_grid(240, 0.04, supersample=3, dtype=torch.float64)  # 9.6″ field
    mag = 18.5
    fluxes = []
    for e1, e2 in [(0.0, 0.0), (0.2, 0.1), (-0.3, 0.2)]:
        sb = sersic_ellipse_from_magnitude(x, y, mag, 0.4, 1.0, e1, e2, 0.03, -0.02)
        fluxes.append(float(bin_supersampled(sb, 3).sum() * 0.04**2))
    assert np.allclose(fluxes, 10 ** (-0.4 * (mag - 25.127)), rtol=2e-4)


def test_sersic_amp_convention_and_roundtrip():
    amp = sersic_amp_from_flux(torch.tensor(3.0, dtype=torch.float64), 0.7, 2.5)
    assert float(sersic_total_flux(amp, 0.7, 2.5)) == pytest.approx(3.0, rel=1e-12)
    # amp is the surface brightness at R = R_s (round profile, on the x axis)
    v = sersic_ellipse(torch.tensor([0.7], dtype=torch.float64), 0.0, amp, 0.7, 2.5, 0.0, 0.0)
    assert float(v) == pytest.approx(float(amp), rel=1e-12)
    assert float(sersic_b_n(4.0)) == pytest.approx(1.9992 * 4 - 0.3271)
    s = SersicEllipse(18.0, 0.8, 2.0)
    assert float(s.flux) == pytest.approx(10 ** (-0.4 * (18 - 25.127)), rel=1e-6)
    with pytest.raises(ValueError, match="r_sersic"):
        SersicEllipse(18.0, -0.8, 2.0)


def test_elliptical_radius_matches_rotated_frame():
    g = torch.Generator().manual_seed(3)
    x, y = torch.randn(2, 500, generator=g, dtype=torch.float64)
    e1, e2 = torch.tensor(0.18, dtype=torch.float64), torch.tensor(-0.11, dtype=torch.float64)
    q, phi = e1e2_to_q_phi(e1, e2)
    xr = torch.cos(phi) * x + torch.sin(phi) * y
    yr = -torch.sin(phi) * x + torch.cos(phi) * y
    assert torch.allclose(
        elliptical_radius_squared(x, y, e1, e2), q * xr**2 + yr**2 / q, rtol=1e-12
    )


def test_sersic_centre_finite_float32_and_precision(dtype):
    x, y = pixel_grid(100, 0.04, supersample=2, dtype=dtype)
    x = torch.cat([x.reshape(-1), torch.zeros(1, dtype=dtype)])  # include the exact centre
    y = torch.cat([y.reshape(-1), torch.zeros(1, dtype=dtype)])
    for r_floor in (1e-4, 0.0):
        sb = sersic_ellipse_from_magnitude(x, y, 17.0, 0.5, 8.0, 0.1, -0.05, r_floor=r_floor)
        assert torch.isfinite(sb).all() and (sb > 0).all()
    # float32 vs float64 agreement over n = 0.5…8
    x64, y64 = x.double(), y.double()
    for n in (0.5, 1.0, 4.0, 8.0):
        a = sersic_ellipse_from_magnitude(x, y, 17.0, 0.8, n, 0.1, -0.05, 0.013, 0.021)
        b = sersic_ellipse_from_magnitude(x64, y64, 17.0, 0.8, n, 0.1, -0.05, 0.013, 0.021)
        rel = ((a.double() - b).abs() / b).max()
        assert rel < (1e-5 if dtype == torch.float32 else 1e-13), (n, float(rel))


def test_sersic_batched_broadcast():
    x, y = pixel_grid(20, 0.04, dtype=torch.float64)
    xb, yb = x.reshape(1, -1), y.reshape(1, -1)
    mags = torch.tensor([[17.0], [18.0], [19.0]], dtype=torch.float64)
    ns = torch.tensor([[1.0], [2.0], [4.0]], dtype=torch.float64)
    out = sersic_ellipse_from_magnitude(xb, yb, mags, 0.8, ns, 0.05, 0.02)
    assert out.shape == (3, 400)
    for k in range(3):
        single = sersic_ellipse_from_magnitude(x, y, float(mags[k]), 0.8, float(ns[k]), 0.05, 0.02)
        assert torch.allclose(out[k], single.reshape(-1), rtol=1e-13)


# ---------------------------------------------------------------------- pixelated


def _stamp(rng, h=20, w=20):
    yy, xx = np.mgrid[:h, :w]
    img = np.exp(-((xx - 8.3) ** 2 + (yy - 11.2) ** 2) / 12.0) + 0.2 * rng.random((h, w))
    return torch.as_tensor(img)


def test_pixelated_flux_conservation_unlensed(rng, dtype):
    stamp = _stamp(rng).to(dtype)
    ds = 0.03
    flux_true = float(stamp.double().sum()) * ds**2
    for order in ("bilinear", "bicubic"):
        # a finer (0.01″), larger grid, rotated and off-centre source
        x, y = pixel_grid(120, 0.01, dtype=dtype)
        sb = pixelated_light(
            x, y, stamp, ds, angle=0.37, center_x=0.05, center_y=-0.04, order=order
        )
        flux = float(sb.double().sum()) * 0.01**2
        assert flux == pytest.approx(flux_true, rel=1e-4), order  # measured ~2e-6


def test_pixelated_rotation_90_equals_rot90(rng, dtype):
    stamp = _stamp(rng, 15, 15).to(dtype)
    ds = 0.05
    x, y = pixel_grid(15, ds, dtype=dtype)
    same = pixelated_light(x, y, stamp, ds)
    assert torch.allclose(same, stamp, atol=1e-6)
    ccw = pixelated_light(x, y, stamp, ds, angle=math.pi / 2)  # counter-clockwise in (x, y)
    assert np.allclose(ccw.numpy(), np.rot90(stamp.numpy(), k=-1), atol=1e-5)
    cw = pixelated_light(x, y, stamp, ds, angle=-math.pi / 2)
    assert np.allclose(cw.numpy(), np.rot90(stamp.numpy(), k=1), atol=1e-5)


def test_pixelated_zero_outside_and_linear_exactness(dtype):
    h, w, ds = 12, 16, 0.1
    u = (torch.arange(w, dtype=dtype) - (w - 1) / 2) * ds
    v = (torch.arange(h, dtype=dtype) - (h - 1) / 2) * ds
    ramp = 2.0 + 0.7 * u[None, :] - 1.3 * v[:, None]
    g = torch.Generator().manual_seed(1)
    # random points inside the hull of the pixel centres, shifted centre
    px = (torch.rand(1000, generator=g, dtype=dtype) - 0.5) * (w - 1) * ds
    py = (torch.rand(1000, generator=g, dtype=dtype) - 0.5) * (h - 1) * ds
    cx, cy = 0.3, -0.2
    val = pixelated_light(px + cx, py + cy, ramp, ds, center_x=cx, center_y=cy)
    exact = 2.0 + 0.7 * px - 1.3 * py
    assert torch.allclose(val, exact, atol=1e-5 if dtype == torch.float32 else 1e-12)
    # one stamp pixel beyond the edge pixel centres and further: exactly zero
    far = torch.tensor([(w + 1) / 2 * ds, -(w + 1) / 2 * ds, 5.0, 0.0], dtype=dtype)
    far_y = torch.tensor([0.0, 0.0, 0.0, (h + 1) / 2 * ds], dtype=dtype)
    assert torch.all(pixelated_light(far + cx, far_y + cy, ramp, ds, center_x=cx, center_y=cy) == 0)


def test_pixelated_batched_padding(rng):
    a = _stamp(rng, 20, 20)
    b = _stamp(rng, 15, 17)
    stamps, off = pad_stamps([a, b])
    assert stamps.shape == (2, 20, 20)
    x, y = pixel_grid(30, 0.02, dtype=torch.float64)
    xb = x.reshape(1, -1).expand(2, -1)
    yb = y.reshape(1, -1).expand(2, -1)
    ds = torch.tensor([[0.03], [0.025]], dtype=torch.float64)
    ang = torch.tensor([[0.3], [-1.1]], dtype=torch.float64)
    out = pixelated_light(
        xb, yb, stamps, ds, ang, 0.01, 0.02, stamp_offset_x=off[:, 0:1], stamp_offset_y=off[:, 1:2]
    )
    assert out.shape == (2, 900)
    for k, s in enumerate([a, b]):
        single = pixelated_light(x, y, s, float(ds[k]), float(ang[k]), 0.01, 0.02)
        assert torch.allclose(out[k], single.reshape(-1), atol=1e-12)
    with pytest.raises(ValueError, match="leading batch dimension"):
        pixelated_light(x, y, stamps, 0.03)
    with pytest.raises(ValueError, match="order"):
        pixelated_light(x, y, a, 0.03, order="cubic")
