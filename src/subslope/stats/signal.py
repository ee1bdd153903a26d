"""The ideal observer's signal: how far a perturbation of an image stands above its noise.

For a noise-free image pair that differs by ``d = I_with − I_without`` (e⁻/s per pixel)
under Gaussian pixel noise of standard deviation ``σ`` (per pixel) the best test of "is
the perturbation there?" has the noise-weighted squared norm

    Δχ² = dᵀ C⁻¹ d,       C = diag(σ) K Kᵀ diag(σ),

summed over the pixels the estimator sees. ``K`` is the noise-correlation filter of the
instrument: the separable kernel ``(w, 1, w)/√(1 + 2w²)`` along each pixel axis
(drizzled pixels; ``w = 0``: independent pixels, ``K = 1``). :func:`whiten` applies
``K⁻¹`` to ``d/σ`` by division in Fourier space (periodic boundary: exact away from the
image border, which the estimator's mask never reaches), so that
``Δχ² = Σ_mask (K⁻¹ d/σ)²`` (:func:`delta_chi2`). Restricting the whitened field to the
mask, rather than inverting the masked covariance, is the one approximation.

A real analysis also refits the smooth model. To first order a change ``δp`` of its
parameters adds ``J δp`` to the image (``J``: derivatives of the subhalo-free image), so
the part of ``d`` that no smooth change can absorb is the residual of the weighted
least-squares fit of ``d`` by the columns of ``J``; its Δχ² is at most the fixed-model
one. A subhalo population can look like a finite change of the lens, which that
first-order fit does not reach: :func:`gauss_newton_refit` returns both, the first
step's (linearised) value and the iterated fit's nonlinear minimum. With the source
morphology held fixed both are upper bounds of what an analysis with a free source
could detect.

Δχ² ≈ 1 is invisible, ≳ 25 an individual detection for a perfect model; over independent
images Δχ² adds.
"""

from __future__ import annotations

import numpy as np

__all__ = ["delta_chi2", "gauss_newton_refit", "whiten"]


def _axis_transfer(n: int, w: float) -> np.ndarray:
    """Discrete Fourier transform of the periodic kernel ``(w, 1, w)/√(1 + 2w²)`` of
    length ``n``: ``(1 + 2w cos 2πk/n)/√(1 + 2w²)``, positive for ``w < 1/2``."""
    k = np.fft.fftfreq(n)
    return (1.0 + 2.0 * w * np.cos(2.0 * np.pi * k)) / np.sqrt(1.0 + 2.0 * w * w)


def whiten(field, sigma, w: float = 0.0) -> np.ndarray:
    """``K⁻¹(field/σ)`` over the last two axes, float64: the field in units of the noise,
    decorrelated (module docstring). ``w``: side weight of the correlation kernel
    (:func:`subslope.physics.instrument.noise_kernel_weight` of the lag-1 correlation),
    in ``[0, 1/2)``."""
    if not 0.0 <= w < 0.5:
        raise ValueError(f"kernel side weight w must be in [0, 0.5), got {w!r}")
    sigma = np.asarray(sigma, dtype=np.float64)
    if np.any(~(sigma > 0)):
        raise ValueError("sigma must be positive and finite at every pixel")
    x = np.asarray(field, dtype=np.float64) / sigma
    if w == 0.0:
        return x
    ny, nx = x.shape[-2:]
    transfer = _axis_transfer(ny, w)[:, None] * _axis_transfer(nx, w)[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(x, axes=(-2, -1)) / transfer, axes=(-2, -1)))


def delta_chi2(diff, sigma, mask, w: float = 0.0) -> float:
    """``Σ_mask (K⁻¹ diff/σ)²`` of one image ``(H, W)``: the ideal observer's Δχ² of the
    perturbation ``diff`` with every other parameter known."""
    mask = np.asarray(mask, dtype=bool)
    return float(np.sum(whiten(diff, sigma, w)[mask] ** 2))


def gauss_newton_refit(
    residual, n_params: int, *, iterations: int = 6, halvings: int = 8, rtol: float = 1e-3
) -> tuple[float, float, int]:
    """Refit the smooth model in full: Gauss-Newton on ``residual(u)``, the whitened masked
    residual vector (data − model at offsets ``u``, in units of each parameter's
    difference step), from ``u = 0``.

    Each iteration takes the Jacobian by central differences of unit steps at the current
    point, ``J_k = (r(u − e_k) − r(u + e_k))/2``, solves ``J δ = r`` by least squares and
    halves ``δ`` (at most ``halvings`` times) until χ² = |r|² falls; it stops after
    ``iterations`` iterations, when no halving lowers χ², or when an iteration lowers it
    by less than ``rtol`` of itself. Returns ``(linearised, full, iterations done)``: the
    χ² the first step predicts (the linearised refit: the least-squares residual of
    ``r(0)`` by the columns of the Jacobian at u = 0)
    and the χ² actually reached, which a nonlinear model can leave far below the
    linearised value (never above the fixed-model χ² |r(0)|²)."""
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations!r}")
    u = np.zeros(int(n_params))
    r = np.asarray(residual(u), dtype=np.float64)
    chi2 = float(r @ r)
    if n_params == 0:
        return chi2, chi2, 0
    eye = np.eye(int(n_params))
    linear: float | None = None
    done = 0
    while done < iterations:
        done += 1
        jac = np.stack([(residual(u - e) - residual(u + e)) / 2.0 for e in eye], axis=1)
        step, *_ = np.linalg.lstsq(jac, r, rcond=None)
        if linear is None:
            left = r - jac @ step
            linear = float(left @ left)
        for _ in range(halvings + 1):
            trial = np.asarray(residual(u + step), dtype=np.float64)
            if float(trial @ trial) < chi2:
                break
            step = step / 2.0
        else:
            break
        gain = chi2 - float(trial @ trial)
        u, r, chi2 = u + step, trial, float(trial @ trial)
        if gain < rtol * chi2:
            break
    return (chi2 if linear is None else linear), chi2, done
