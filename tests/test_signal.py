"""The ideal observer's Δχ² (subslope.stats.signal) against images whose value is known
in closed form, the linearised refit's limits, and correlated noise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.physics.instrument import correlate_noise, noise_kernel_weight
from subslope.stats.signal import delta_chi2, gauss_newton_refit, whiten

N = 64


def refit_delta_chi2(diff, jacobian, sigma, mask, w: float = 0.0) -> float:
    """The linearised refit's Δχ² in closed form, the reference of these tests: the
    residual of the weighted least-squares fit of ``diff`` by the columns of ``jacobian``
    ``(P, H, W)`` inside ``mask`` (minimum-norm for degenerate columns)."""
    mask = np.asarray(mask, dtype=bool)
    b = whiten(diff, sigma, w)[mask]
    jac = np.asarray(jacobian, dtype=np.float64)
    if jac.shape[0] == 0:
        return float(np.sum(b**2))
    a = np.stack([whiten(col, sigma, w)[mask] for col in jac], axis=1)
    coef, *_ = np.linalg.lstsq(a, b, rcond=None)
    return float(np.sum((b - a @ coef) ** 2))


def _grid():
    y, x = np.mgrid[:N, :N] - (N - 1) / 2
    return x, y


def test_gaussian_blob_matches_its_closed_form():
    """A Gaussian of amplitude A and width s on a pixel grid, σ constant: Σ (A/σ)² e^{−r²/s²}
    is (A/σ)² π s² for s of a few pixels (the sum of a smooth Gaussian is its integral)."""
    x, y = _grid()
    amp, s, sigma = 0.3, 4.0, 0.05
    blob = amp * np.exp(-(x**2 + y**2) / (2 * s**2))
    mask = np.ones((N, N), bool)
    expect = (amp / sigma) ** 2 * np.pi * s**2
    assert delta_chi2(blob, np.full((N, N), sigma), mask) == pytest.approx(expect, rel=1e-9)


def test_mask_and_pixel_sigma_weight_the_sum():
    d = np.ones((N, N))
    sigma = np.full((N, N), 2.0)
    mask = np.zeros((N, N), bool)
    mask[:10, :5] = True
    assert delta_chi2(d, sigma, mask) == pytest.approx(50 / 4)


def test_correlated_noise_is_whitened_exactly_in_the_interior():
    """d = σ·K(u) with the instrument's own correlation filter: whitening returns u, so
    Δχ² over an interior mask is Σ u² there."""
    rng = np.random.default_rng(1)
    u = rng.normal(size=(N, N))
    rho = 0.4
    sigma = np.full((N, N), 0.1)
    d = sigma * correlate_noise(torch.as_tensor(u), rho).numpy()
    mask = np.zeros((N, N), bool)
    mask[8:-8, 8:-8] = True
    w = noise_kernel_weight(rho)
    # K⁻¹ has infinite support, so the border (no periodic wrap there) reaches the
    # interior at (w/(1 + √(1 − 4w²)))^8 ~ 1e-6 relative
    assert delta_chi2(d, sigma, mask, w) == pytest.approx(float(np.sum(u[mask] ** 2)), rel=1e-6)
    # for a smooth perturbation the correlated noise is stronger than σ alone says, so
    # leaving the correlation out overstates the signal by ((1 + 2w)²/(1 + 2w²))²
    x, y = _grid()
    blob = np.exp(-(x**2 + y**2) / 50.0)
    smooth = sigma * correlate_noise(torch.as_tensor(blob), rho).numpy()
    gain = ((1 + 2 * w) ** 2 / (1 + 2 * w * w)) ** 2
    assert delta_chi2(smooth, sigma, mask) / delta_chi2(smooth, sigma, mask, w) == pytest.approx(
        gain, rel=0.05
    )


def test_refit_absorbs_what_the_smooth_model_can_and_keeps_what_it_cannot():
    x, y = _grid()
    sigma = np.full((N, N), 0.1)
    mask = x**2 + y**2 < 25**2
    jac = np.stack([np.exp(-(x**2 + y**2) / 200), x / N, np.ones((N, N))])
    inside = 0.3 * jac[0] - 2.0 * jac[1] + 0.01 * jac[2]
    assert refit_delta_chi2(inside, jac, sigma, mask) == pytest.approx(0.0, abs=1e-12)
    bump = np.exp(-((x - 7) ** 2 + (y + 3) ** 2) / 2.0)
    fixed = delta_chi2(bump, sigma, mask)
    refit = refit_delta_chi2(bump, jac, sigma, mask)
    assert 0 < refit <= fixed
    # a component orthogonal to every column is left whole
    odd = np.where(mask, np.sign(x) * np.sign(y), 0.0) * (x != 0) * (y != 0)
    assert refit_delta_chi2(odd, jac, sigma, mask) == pytest.approx(
        delta_chi2(odd, sigma, mask), rel=1e-9
    )
    # degenerate (zero) columns change nothing
    padded = np.concatenate([jac, np.zeros((2, N, N))])
    assert refit_delta_chi2(bump, padded, sigma, mask) == pytest.approx(refit, rel=1e-9)


def _blob(cx, cy, amp=1.0, width=3.0):
    x, y = _grid()
    return amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * width**2))


def test_full_refit_reaches_the_minimum_a_linearised_one_cannot():
    """A blob moved by 2.5 px, refitted by the blob's position (steps of 0.1 px): the model
    holds the data exactly, so the full refit leaves ~0; the first-order fit of a 2.5 px
    shift (almost a blob width) leaves a large part. A model linear in its parameters is
    fitted in one step, and then both agree with refit_delta_chi2."""
    sigma = np.full((N, N), 0.05)
    mask = np.ones((N, N), dtype=bool)
    data = _blob(2.5, -1.0)

    def residual(u):
        return whiten(data - _blob(0.1 * u[0], 0.1 * u[1]), sigma)[mask]

    fixed = float(np.sum(residual(np.zeros(2)) ** 2))
    linear, full, done = gauss_newton_refit(residual, 2, iterations=20)
    assert full < 1e-6 * fixed and full <= linear < fixed and linear > 0.05 * fixed
    assert 1 < done <= 20
    # one iteration: the linearised refit and nothing more
    one = gauss_newton_refit(residual, 2, iterations=1)
    assert one[0] == pytest.approx(linear, rel=1e-12) and one[2] == 1 and one[1] < fixed
    # linear in the parameters (amplitudes of fixed shapes): exact in one step
    shapes = np.stack([_blob(0, 0), _blob(5, 5, width=2.0)])
    target = 0.7 * shapes[0] - 0.2 * shapes[1] + _blob(-9, 4, 0.3, 1.0)

    def linear_residual(u):
        return whiten(target - 0.01 * np.tensordot(u, shapes, axes=1), sigma)[mask]

    lin, full_lin, _ = gauss_newton_refit(linear_residual, 2, iterations=6)
    expected = refit_delta_chi2(target, shapes, sigma, mask)
    assert lin == pytest.approx(expected, rel=1e-8) and full_lin == pytest.approx(
        expected, rel=1e-8
    )
    # nothing to refit: the fixed-model value
    assert gauss_newton_refit(lambda u: residual(np.zeros(2)), 0) == pytest.approx(
        (fixed, fixed, 0)
    )
    with pytest.raises(ValueError, match="iterations"):
        gauss_newton_refit(residual, 2, iterations=0)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="sigma"):
        whiten(np.ones((4, 4)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match="w must be"):
        whiten(np.ones((4, 4)), np.ones((4, 4)), 0.6)
