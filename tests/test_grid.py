"""Pixel grid centring and supersample binning."""

import pytest
import torch

from subslope.physics.grid import axis_coordinates, bin_supersampled, pixel_grid


def test_grid_centring_and_symmetry(dtype):
    x, y = pixel_grid(100, 0.04, dtype=dtype)
    assert x.shape == y.shape == (100, 100) and x.dtype == dtype
    # x_i = (i - 49.5)·0.04; row index ↔ y, column index ↔ x
    assert torch.allclose(x[0, :3], torch.tensor([-1.98, -1.94, -1.90], dtype=dtype))
    assert float(x[7, 0]) == pytest.approx(-1.98) and float(y[0, 7]) == pytest.approx(-1.98)
    assert float(x[0, 50]) == pytest.approx(0.02) and float(y[50, 0]) == pytest.approx(0.02)
    assert torch.equal(x, y.T)
    assert torch.allclose(x, -x.flip(-1), atol=0) and torch.allclose(y, -y.flip(-2), atol=0)
    assert float(x.mean()) == pytest.approx(0.0, abs=1e-6)


def test_supersampled_subpixels_average_to_pixel_centres(dtype):
    k = 4
    x1, y1 = pixel_grid(10, 0.04, dtype=dtype)
    xk, yk = pixel_grid(10, 0.04, supersample=k, dtype=dtype)
    assert xk.shape == (40, 40)
    # sub-pixel spacing Δ/k, symmetric about each pixel centre
    assert torch.allclose(xk[0, 1] - xk[0, 0], torch.tensor(0.01, dtype=dtype))
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    assert torch.allclose(bin_supersampled(xk, k), x1, atol=tol)
    assert torch.allclose(bin_supersampled(yk, k), y1, atol=tol)
    # the mean of a linear function is preserved (value at the pixel centre)
    lin = 3.0 * xk - 2.0 * yk + 0.7
    assert torch.allclose(bin_supersampled(lin, k), 3.0 * x1 - 2.0 * y1 + 0.7, atol=10 * tol)


def test_bin_supersampled_batched_and_errors():
    img = torch.arange(2 * 3 * 6 * 6, dtype=torch.float64).reshape(2, 3, 6, 6)
    out = bin_supersampled(img, 3)
    assert out.shape == (2, 3, 2, 2)
    assert float(out[1, 2, 1, 0]) == pytest.approx(float(img[1, 2, 3:6, 0:3].mean()))
    assert torch.allclose(out.sum((-2, -1)) * 9, img.sum((-2, -1)))
    with pytest.raises(ValueError, match="divisible by k"):
        bin_supersampled(img, 4)
    with pytest.raises(ValueError, match="supersample"):
        pixel_grid(10, 0.04, supersample=0)
    with pytest.raises(ValueError, match="pixel_scale"):
        axis_coordinates(10, -0.04)
