"""PSF loading/degrading, convolution and noise."""

import math

import numpy as np
import pytest
import torch

from subslope.physics.instrument import (
    Instrument,
    add_noise,
    convolve,
    correlate_noise,
    degrade_psf,
    fft_size,
    gaussian_psf,
    kernel_spectrum,
    load_empirical_psf,
    noise_kernel_weight,
    noise_sigma_map,
    psf_fwhm,
)


def _centroid(k):
    k = torch.as_tensor(k, dtype=torch.float64)
    i = torch.arange(k.shape[0], dtype=torch.float64) - k.shape[0] // 2
    return float((k.sum(0) * i).sum() / k.sum()), float((k.sum(1) * i).sum() / k.sum())


@pytest.fixture
def psf_file(data_dir):
    path = data_dir / "psf" / "emp_psf_f814w.fits"
    if not path.is_file():
        pytest.skip(f"PSF file not found: {path}")
    return path


# ---------------------------------------------------------------------------- PSF


@pytest.mark.parametrize("which", [17, (3, 2), "mean"])
def test_empirical_psf_properties(data_dir, which):
    path = data_dir / "psf" / "emp_psf_f814w.fits"
    k = load_empirical_psf(path, which)
    assert k.dtype == torch.float64 and k.shape == (25, 25) and k.shape[0] % 2 == 1
    assert float(k.sum()) == pytest.approx(1.0, abs=1e-12)
    assert (k >= 0).all()
    assert int(k.argmax()) == 12 * 25 + 12  # peak on the central pixel
    cx, cy = _centroid(k)
    assert abs(cx) < 0.05 and abs(cy) < 0.05
    fwhm = psf_fwhm(k, 0.04)
    assert 0.065 < fwhm < 0.12  # measured 0.079″ for PSF 17 (WFC3/UVIS F814W library)


def test_empirical_psf_index_and_crop(psf_file):
    a = load_empirical_psf(psf_file, 17)
    b = load_empirical_psf(psf_file, (3, 2))  # k = iy·NXPSFS + ix = 2·7 + 3
    assert torch.equal(a, b)
    small = load_empirical_psf(psf_file, 17, out_size=11, dtype=torch.float32)
    assert small.shape == (11, 11) and small.dtype == torch.float32
    assert float(small.sum()) == pytest.approx(1.0, abs=1e-6)
    # edge PSFs carry a line of −0.1 flags: clipped, still valid
    edge = load_empirical_psf(psf_file, (6, 3))
    assert (edge >= 0).all() and float(edge.sum()) == pytest.approx(1.0)
    off = load_empirical_psf(psf_file, 17, negative="offset")
    # the paltas-style offset adds a flat pedestal: ~2% of the flux moves to the wings
    assert (off >= 0).all() and float((off - a).abs().max()) < 5e-3
    assert 0.005 < float(off[:3].sum() - a[:3].sum()) * 625 / 75 < 0.05
    with pytest.raises(ValueError, match="which"):
        load_empirical_psf(psf_file, 56)
    with pytest.raises(ValueError, match="out_size"):
        load_empirical_psf(psf_file, 17, out_size=10)
    with pytest.raises(ValueError, match="path"):
        load_empirical_psf(psf_file.parent / "missing.fits")


def test_degrade_keeps_centre_and_centroid():
    # an off-centre Gaussian blob on a 101×101, 4× supersampled grid
    i = np.arange(101) - 50
    for dx, dy in [(0.0, 0.0), (1.0, -2.0), (3.0, 0.5)]:
        p = np.exp(-((i[None, :] - dx) ** 2 + (i[:, None] - dy) ** 2) / (2 * 6.0**2))
        for method in ("sum", "sample"):
            k = degrade_psf(p, 4, method)
            assert k.shape == (25, 25)
            cx, cy = _centroid(k)
            assert cx == pytest.approx(dx / 4, abs=2e-3) and cy == pytest.approx(dy / 4, abs=2e-3)
    # block sum conserves the flux of a compact PSF; sum-of-blocks weights [½,1,1,1,½]
    k = degrade_psf(p, 4, "sum")
    assert k.sum() == pytest.approx(p.sum(), rel=1e-9)
    delta = np.zeros((101, 101))
    delta[50, 52] = 1.0  # on a block boundary: split evenly between two output pixels
    kd = degrade_psf(delta, 4, "sum")
    assert kd[12, 12] == pytest.approx(0.5) and kd[12, 13] == pytest.approx(0.5)


def test_gaussian_psf_fwhm_and_moments():
    fwhm, pix = 0.1, 0.04
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2))) / pix
    g = gaussian_psf(fwhm, pix)
    assert g.shape == (13, 13) and float(g.sum()) == pytest.approx(1.0)
    i = torch.arange(13, dtype=torch.float64) - 6
    var = float((g.sum(0) * i**2).sum())
    assert var == pytest.approx(sigma**2 + 1.0 / 12.0, rel=1e-3)  # pixel-integrated
    gs = gaussian_psf(fwhm, pix, 41, integrate=False)
    assert float((gs.sum(0) * (torch.arange(41) - 20.0) ** 2).sum()) == pytest.approx(
        sigma**2, rel=1e-6
    )
    assert psf_fwhm(gs, pix) == pytest.approx(fwhm, rel=0.03)
    assert psf_fwhm(gaussian_psf(0.2, pix, 41, integrate=False), pix) == pytest.approx(
        0.2, rel=0.03
    )
    with pytest.raises(ValueError, match="size"):
        gaussian_psf(fwhm, pix, 12)


# --------------------------------------------------------------------- convolution


def test_fft_and_direct_agree(dtype):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(3, 2, 40, 37, generator=g, dtype=torch.float64).to(dtype)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    for shape in [(5, 5), (13, 13), (25, 25), (3, 7)]:
        k = torch.rand(shape, generator=g, dtype=torch.float64).to(dtype)
        k = k / k.sum()
        a = convolve(img, k, "direct")
        b = convolve(img, k, "fft")
        assert a.shape == img.shape and a.dtype == dtype
        assert torch.allclose(a, b, atol=tol * float(img.max())), shape
        assert torch.allclose(convolve(img, k), b, atol=tol)


def test_convolution_is_a_true_convolution_and_conserves_flux():
    k = torch.zeros(5, 5, dtype=torch.float64)
    k[2, 3] = 1.0  # shifts by +1 column (+x) under convolution
    img = torch.zeros(1, 20, 20, dtype=torch.float64)
    img[0, 10, 10] = 1.0
    for m in ("direct", "fft"):
        out = convolve(img, k, m)
        assert float(out[0, 10, 11]) == pytest.approx(1.0) and float(out.sum()) == pytest.approx(
            1.0
        )
    # a compact source away from the edges keeps its flux
    x = torch.arange(60, dtype=torch.float64) - 29.5
    src = torch.exp(-(x[None, :] ** 2 + x[:, None] ** 2) / 20.0)
    psf = gaussian_psf(0.1, 0.04)
    for m in ("direct", "fft"):
        assert float(convolve(src, psf, m).sum()) == pytest.approx(float(src.sum()), rel=1e-10)
    # zero padding: a flat image loses flux only within the kernel half-width of the edge
    flat = torch.ones(30, 30, dtype=torch.float64)
    out = convolve(flat, psf)
    assert torch.allclose(out[6:-6, 6:-6], torch.ones(18, 18, dtype=torch.float64))
    assert float(out[0, 0]) < 0.5


# --------------------------------------------------------------------------- noise


def test_instrument_numbers():
    inst = Instrument()
    sky = 10 ** (-0.4 * (21.83 - 25.127)) * 0.04**2
    assert inst.sky_per_pixel == pytest.approx(sky)
    assert inst.background_sigma == pytest.approx(math.sqrt(sky * 2200 + 9.0) / 2200)
    img = torch.tensor([-1.0, 0.0, 1.0, 100.0], dtype=torch.float64)
    sig = noise_sigma_map(img)
    assert float(sig[0]) == pytest.approx(inst.background_sigma)  # negatives clamped
    assert float(sig[3]) == pytest.approx(math.sqrt(100 * 2200 + sky * 2200 + 9) / 2200)
    with pytest.raises(ValueError, match="exposure_time"):
        Instrument(exposure_time=0.0)


@pytest.mark.parametrize("poisson", ["exact", "gaussian"])
def test_noise_variance_matches_sigma_map(poisson):
    levels = torch.tensor([0.0, 0.003, 0.03, 0.3, 3.0, 30.0], dtype=torch.float64)
    img = levels.repeat(4000, 1)  # 4000 independent draws of each level
    noisy = add_noise(img, 123, poisson=poisson)
    resid = noisy - img
    var = resid.var(dim=0)
    expect = noise_sigma_map(levels) ** 2
    assert torch.allclose(var, expect, rtol=0.08)  # per level, ~2.2% statistical error
    assert float((var / expect).mean()) == pytest.approx(1.0, abs=0.03)
    assert float(resid.mean(0).abs().max() / noise_sigma_map(levels).max()) < 0.1


def test_noise_seeded_and_reproducible(dtype):
    img = torch.rand(
        2, 100, 100, generator=torch.Generator().manual_seed(5), dtype=torch.float64
    ).to(dtype)
    a = add_noise(img, 7)
    b = add_noise(img, torch.Generator().manual_seed(7))
    c = add_noise(img, 8)
    assert a.dtype == dtype and a.shape == img.shape
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert torch.isfinite(a).all()
    inst = Instrument(read_noise=0.0, sky_brightness=40.0)  # almost pure shot noise
    d = inst.add_noise(img.double() * 0 + 1.0, 9)
    assert torch.allclose(d * 2200, torch.round(d * 2200), atol=1e-6)  # integer electron counts
    with pytest.raises(ValueError, match="generator"):
        add_noise(img, "seed")


def _lag_correlation(field, dy, dx):
    a, b = field[..., : field.shape[-2] - dy, : field.shape[-1] - dx], field[..., dy:, dx:]
    return float((a * b).mean() / (a.std() * b.std()))


@pytest.mark.parametrize("rho", [0.2, 0.4, 0.6])
def test_correlated_noise_has_the_lag_correlations_of_its_kernel(rho):
    w = noise_kernel_weight(rho)
    assert 2 * w / (1 + 2 * w * w) == pytest.approx(rho, rel=1e-12)
    white = torch.randn(64, 96, 96, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    field = correlate_noise(white, rho)
    inner = field[:, 1:-1, 1:-1]
    assert float(inner.var()) == pytest.approx(1.0, abs=0.01)
    assert float(field[:, :, 0].var()) == pytest.approx(1.0, abs=0.03)  # border kept too
    small = torch.randn(
        20000, 3, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64
    )
    assert correlate_noise(small, rho).var(0).sub(1).abs().max() < 0.05  # corners and edges
    assert _lag_correlation(inner, 0, 1) == pytest.approx(rho, abs=0.005)
    assert _lag_correlation(inner, 1, 0) == pytest.approx(rho, abs=0.005)
    assert _lag_correlation(inner, 1, 1) == pytest.approx(rho * rho, abs=0.005)
    assert _lag_correlation(inner, 0, 2) == pytest.approx(w * w / (1 + 2 * w * w), abs=0.005)
    assert _lag_correlation(inner, 0, 3) == pytest.approx(0.0, abs=0.005)


def test_uncorrelated_noise_is_the_independent_draw_bit_for_bit():
    img = torch.rand(3, 40, 40, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    plain = add_noise(img, 11)
    assert torch.equal(add_noise(img, 11, instrument=Instrument(noise_correlation=0.0)), plain)
    white = torch.randn(5, 7, generator=torch.Generator().manual_seed(3))
    assert correlate_noise(white, 0.0) is white


def test_a_correlation_range_draws_one_value_per_image_after_its_noise():
    img = torch.full((1, 64, 64), 0.05, dtype=torch.float64)
    ranged = Instrument(noise_correlation=(0.3, 0.5))
    a, b = add_noise(img, 21, instrument=ranged), add_noise(img, 21, instrument=ranged)
    assert torch.equal(a, b)  # the image's seed fixes its correlation
    g = torch.Generator().manual_seed(21)
    lam = (img + ranged.sky_per_pixel) * ranged.total_exposure_time
    shot = torch.poisson(lam, generator=g) - lam
    read = ranged.read_noise * torch.randn(img.shape, generator=g, dtype=torch.float64)
    rho = 0.3 + 0.2 * float(torch.rand((), generator=g, dtype=torch.float64))
    white = (shot + read) / ranged.total_exposure_time
    torch.testing.assert_close(a, img + correlate_noise(white, rho), rtol=0, atol=1e-15)
    drawn = []
    for seed in range(40):
        noise = add_noise(img, seed, instrument=ranged) - img
        drawn.append(_lag_correlation(noise[0, 1:-1, 1:-1], 0, 1))
    assert 0.25 < min(drawn) and max(drawn) < 0.57 and np.std(drawn) > 0.03


@pytest.mark.parametrize(
    "bad", [-0.1, 0.71, 1.0, (0.5, 0.3), (0.2, 0.8), (0.1, 0.2, 0.3), "0.3", float("nan")]
)
def test_noise_correlation_outside_its_range_is_refused(bad):
    with pytest.raises(ValueError, match="noise_correlation must be a number in"):
        Instrument(noise_correlation=bad)


# ----------------------------------------------------------------------------- GPU


@pytest.mark.gpu
def test_cuda_matches_cpu():
    from subslope.physics.grid import pixel_grid
    from subslope.physics.light import pixelated_light, sersic_ellipse_from_magnitude

    dev = torch.device("cuda")
    x, y = pixel_grid(100, 0.04, supersample=2, dtype=torch.float64)
    args = (18.0, 0.8, 4.0, 0.1, -0.05, 0.01, 0.02)
    cpu = sersic_ellipse_from_magnitude(x, y, *args)
    gpu = sersic_ellipse_from_magnitude(x.to(dev), y.to(dev), *args)
    assert gpu.device.type == "cuda" and torch.allclose(gpu.cpu(), cpu, rtol=1e-12)
    stamp = torch.rand(30, 30, dtype=torch.float64)
    p_cpu = pixelated_light(x, y, stamp, 0.03, 0.4)
    p_gpu = pixelated_light(x.to(dev), y.to(dev), stamp.to(dev), 0.03, 0.4)
    assert torch.allclose(p_gpu.cpu(), p_cpu, atol=1e-12)
    psf = gaussian_psf(0.1, 0.04, device=dev)
    img = cpu[None].repeat(3, 1, 1)
    for m in ("direct", "fft", "auto"):
        out = convolve(img.to(dev), psf, m)
        assert out.device.type == "cuda"
        assert torch.allclose(out.cpu(), convolve(img, psf.cpu(), "fft"), rtol=1e-9, atol=1e-12)
    n1 = add_noise(img.to(dev), 11)
    n2 = add_noise(img.to(dev), 11)
    assert n1.device.type == "cuda" and torch.equal(n1, n2)
    var = (add_noise(torch.full((200000,), 1.0, device=dev, dtype=torch.float64), 3) - 1.0).var()
    assert float(var) == pytest.approx(float(noise_sigma_map(torch.tensor(1.0)) ** 2), rel=0.03)


def test_fft_size_is_the_smallest_2_3_smooth_length():
    def smooth(n):
        for p in (2, 3):
            while n % p == 0:
                n //= p
        return n == 1

    for n in range(1, 400):
        s = fft_size(n)
        assert s >= n and smooth(s)
        assert not any(smooth(k) for k in range(n, s))
    assert fft_size(124) == 128  # a 100-pixel image and a 25-pixel PSF
    with pytest.raises(ValueError, match="n = 0"):
        fft_size(0)


def test_convolution_with_a_precomputed_kernel_spectrum():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(3, 40, 40, generator=g, dtype=torch.float64)
    k = torch.rand(9, 9, generator=g, dtype=torch.float64)
    k = k / k.sum()
    spec = kernel_spectrum(k, (40, 40))
    assert spec.shape == (fft_size(48), fft_size(48))
    assert torch.equal(convolve(img, k, "fft", spectrum=spec), convolve(img, k, "fft"))
    torch.testing.assert_close(convolve(img, k, "fft", spectrum=spec), convolve(img, k, "direct"))
    with pytest.raises(ValueError, match=r"spectrum is for a \(9, 9\) kernel and \(40, 40\)"):
        convolve(img[:, :30, :30], k, "fft", spectrum=spec)
