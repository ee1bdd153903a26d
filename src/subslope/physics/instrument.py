"""The instrument: PSF (empirical HST F814W, Gaussian fallback), convolution, noise.

PSF
---
:func:`load_empirical_psf` reads the 4×-supersampled empirical ("STDPSF", Anderson)
library (``NXPSFS × NYPSFS`` PSFs of 101×101, PSF number ``k = iy·NXPSFS + ix``, x
fastest, at detector positions ``IPSFXnn``/``JPSFYnn``). Steps:

1. pick PSF ``k`` (or ``(ix, iy)``, or the ``'mean'`` of all); the reference analysis
   (paltas HST config) used PSF 17, the default here;
2. negative values → 0 (``negative='clip'``; they are tiny wing residuals, ≈4e-4 of the
   flux, plus a border line of −0.1 flags in the PSFs at the detector/chip edges),
   or ``negative='offset'`` (subtract the minimum, as paltas did);
3. degrade by the supersampling factor ``s`` (= 4) so that the PSF centre (supersampled
   pixel 50) lands on the centre of an output pixel. ``method='sum'`` (default) sums
   ``s × s`` blocks centred on the output pixel centres; for even ``s`` the block edges
   fall on supersampled-pixel centres, so the edge rows/columns get weight ½ (the 1-D
   weights ``[½, 1, 1, 1, ½]`` for s = 4 — the trapezoid rule for the box). This is the
   block sum made symmetric, with no sub-pixel shift. ``method='sample'`` takes every
   s-th sample through the centre, which is the right thing for a true *effective* PSF
   (already pixel-integrated); 'sum' integrates over a pixel once more (slightly
   broader), which is what degrading a supersampled PSF in lenstronomy/paltas does;
4. crop to ``out_size`` (odd) and normalise to sum 1.

:func:`gaussian_psf` integrates a circular Gaussian over each pixel exactly (erf
differences; ``integrate=False`` samples it at pixel centres), truncated to ``size``.

Convolution
-----------
:func:`convolve` is a true convolution (kernel flipped), 'same' output size, with the
image zero-padded outside its borders: flux that the PSF would scatter in from outside
the field is missing and flux scattered out is lost, so only pixels farther than the
kernel half-width from the edge are exact. ``method='direct'`` (``conv2d``) and
``method='fft'`` (``torch.fft.rfft2`` zero-padded to the linear-convolution size,
rounded up to a fast FFT length :func:`fft_size`)
agree to float precision; ``'auto'`` picks the FFT on CPU (measured 3–6× faster
than ``conv2d`` for 100×100 images and kernels of 5–25 pixels, one thread) and direct
on other devices for kernels up to ``DIRECT_MAX_KERNEL`` pixels per side.

Noise (lenstronomy ``SingleBand``, ``data_count_unit='e-'``, the paltas default)
-----
Images are in e⁻/s per pixel; with total exposure ``T = t·N_exp``, sky per pixel
``s = 10^(−0.4 (μ_sky − zp))·Δ²`` (e⁻/s), read noise ``σ_RN`` (e⁻ per exposure)::

    σ² = (max(I, 0)·T + s·T + N_exp·σ_RN²) / T²      [(e⁻/s)²]

Poisson noise acts on electrons, so the gain (e⁻/ADU) enters only to convert to ADU
(kept in :class:`Instrument` for that). :func:`add_noise` draws
``I + (Poisson(λ) − λ + σ_RN√N_exp·z) / T`` with ``λ = (max(I, 0) + s)·T`` (exact
Poisson on image + sky, sky not added back: sky-subtracted images). ``poisson='gaussian'``
uses the normal approximation ``I + σ·z`` as lenstronomy's ``noise_for_model`` does
(fine here: λ ≥ s·T ≈ 73 e⁻ per pixel for the default instrument).

Drizzled images (the HST cutouts: ACS's 0.05″ pixels resampled onto 0.04″) share each
input pixel's noise between neighbouring output pixels. With
``Instrument.noise_correlation`` ρ > 0 the noise field is filtered by
:func:`correlate_noise` (a 3-tap kernel along each axis that keeps every pixel's σ and
gives neighbours the correlation ρ); ρ = 0 is independent pixels, as lenstronomy draws
them. A square-kernel drizzle at this pixel ratio gives ρ ≈ 0.36–0.40 for pixfrac 1 and
0.2–0.35 for pixfrac 0.6–0.8 (``docs/realism.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from subslope.config import schema_defaults

__all__ = [
    "Instrument",
    "load_empirical_psf",
    "degrade_psf",
    "gaussian_psf",
    "psf_fwhm",
    "convolve",
    "convolution_method",
    "fft_size",
    "kernel_spectrum",
    "KernelSpectrum",
    "noise_sigma_map",
    "add_noise",
    "correlate_noise",
    "noise_kernel_weight",
    "MAX_NOISE_CORRELATION",
    "DIRECT_MAX_KERNEL",
]

DIRECT_MAX_KERNEL = 15

#: The instrument of the config schema's defaults (HST ACS F814W): pixel size in
#: arcsec, image side in pixels, AB zero point (magnitude of 1 e⁻/s). Signatures that
#: need a default use these names; the numbers live in the schema only.
_INSTRUMENT = schema_defaults("instrument")
PIXEL_SCALE: float = _INSTRUMENT["pixel_scale"]
NPIX: int = _INSTRUMENT["npix"]
ZERO_POINT: float = _INSTRUMENT["zero_point"]


# ----------------------------------------------------------------------------- PSF


def _read_psf_library(path) -> tuple[np.ndarray, int, int]:
    from astropy.io import fits

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"path: PSF file not found: {path}")
    import warnings

    with warnings.catch_warnings():
        # the STDPSF headers spell NXPSFs/NYPSFs in mixed case; astropy warns on verify
        warnings.simplefilter("ignore")
        with fits.open(path) as hdul:
            data = np.asarray(hdul[0].data, dtype=np.float64)
            header = hdul[0].header
            nx = int(header.get("NXPSFS", 1))
            ny = int(header.get("NYPSFS", 1))
    if data.ndim == 2:
        data = data[None]
    if data.ndim != 3 or data.shape[-1] != data.shape[-2] or data.shape[-1] % 2 == 0:
        raise ValueError(f"path: {path} must hold odd square PSF(s), got shape {data.shape}")
    if nx * ny != data.shape[0]:
        nx, ny = data.shape[0], 1
    return data, nx, ny


def degrade_psf(
    psf_super: np.ndarray | torch.Tensor, factor: int, method: str = "sum"
) -> np.ndarray:
    """Degrade an odd, centred supersampled PSF by an integer ``factor``.

    Output pixel ``m`` is centred on supersampled pixel ``c + factor·m`` (c = centre);
    see the module docstring for ``method`` ('sum' or 'sample'). Returns an odd square
    float64 array (not normalised).
    """
    p = np.asarray(psf_super, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] != p.shape[1] or p.shape[0] % 2 == 0:
        raise ValueError(f"psf_super must be an odd square 2-D array, got shape {p.shape}")
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor must be a positive integer, got {factor!r}")
    if method not in ("sum", "sample"):
        raise ValueError(f"method must be 'sum' or 'sample', got {method!r}")
    n = p.shape[0]
    c = n // 2
    m = c // factor  # output half-width (every output centre inside the input)
    if factor == 1:
        return p.copy()
    if method == "sum":
        h = factor // 2
        w1 = np.ones(2 * h + 1)
        if factor % 2 == 0:
            w1[0] = w1[-1] = 0.5
        pp = np.pad(p, h)
        # separable box filter centred on each supersampled pixel
        rows = sum(w1[t] * pp[t : t + n, :] for t in range(2 * h + 1))
        box = sum(w1[t] * rows[:, t : t + n] for t in range(2 * h + 1))
    else:
        box = p
    idx = c + factor * np.arange(-m, m + 1)
    return box[np.ix_(idx, idx)]


def load_empirical_psf(
    path,
    which: int | tuple[int, int] | str = 17,
    *,
    supersampling: int = 4,
    out_size: int | None = None,
    negative: str = "clip",
    method: str = "sum",
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Empirical PSF kernel at the image pixel scale, normalised to sum 1.

    Parameters
    ----------
    path : str or Path
        STDPSF-style FITS file (e.g. ``<data>/psf/emp_psf_f814w.fits``).
    which : int, (ix, iy) or 'mean'
        PSF number ``k = iy·NXPSFS + ix``, grid indices, or the average of all PSFs
        (each made non-negative first). Default 17, the reference analysis' choice.
    supersampling : int
        Supersampling factor of the file (4); the degrade factor.
    out_size : int or None
        Odd side of the returned kernel (cropped about the centre); None = largest
        available (25 for 101 supersampled pixels and factor 4).
    negative : {'clip', 'offset'}
        Negative values set to 0, or the minimum subtracted (paltas).
    method : {'sum', 'sample'}
        Degrading scheme, see module docstring.
    """
    data, nx, ny = _read_psf_library(path)
    if negative not in ("clip", "offset"):
        raise ValueError(f"negative must be 'clip' or 'offset', got {negative!r}")

    def fix(p):
        return np.clip(p, 0.0, None) if negative == "clip" else p - min(p.min(), 0.0)

    if isinstance(which, str):
        if which != "mean":
            raise ValueError(f"which must be an int, (ix, iy) or 'mean', got {which!r}")
        psf = np.mean([fix(p) for p in data], axis=0)
    else:
        if isinstance(which, tuple):
            if len(which) != 2 or not (0 <= which[0] < nx and 0 <= which[1] < ny):
                raise ValueError(f"which=(ix, iy) must be within ({nx}, {ny}), got {which!r}")
            k = which[1] * nx + which[0]
        else:
            k = int(which)
        if not 0 <= k < data.shape[0]:
            raise ValueError(f"which must be in [0, {data.shape[0]}), got {which!r}")
        psf = fix(data[k])
    kern = degrade_psf(psf, supersampling, method)
    if out_size is not None:
        if (
            isinstance(out_size, bool)
            or not isinstance(out_size, int)
            or out_size < 1
            or out_size % 2 == 0
        ):
            raise ValueError(f"out_size must be a positive odd integer, got {out_size!r}")
        if out_size > kern.shape[0]:
            raise ValueError(
                f"out_size={out_size} exceeds the available kernel size {kern.shape[0]}"
            )
        cut = (kern.shape[0] - out_size) // 2
        kern = kern[cut : kern.shape[0] - cut, cut : kern.shape[0] - cut]
    total = kern.sum()
    if not total > 0:
        raise ValueError(f"path: PSF {which!r} in {path} has no positive flux")
    return torch.as_tensor(kern / total, dtype=dtype, device=device)


def gaussian_psf(
    fwhm: float = 0.1,
    pixel_scale: float = PIXEL_SCALE,
    size: int | None = None,
    *,
    integrate: bool = True,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """Circular Gaussian PSF kernel (sum 1), odd ``size`` (default: covers ±5σ).

    ``integrate=True`` integrates the Gaussian over each pixel (erf differences),
    so its variance is σ² + Δ²/12 per axis (untruncated); False samples it at the
    pixel centres. ``fwhm`` and ``pixel_scale`` in arcsec.
    """
    if not fwhm > 0:
        raise ValueError(f"fwhm must be > 0 arcsec, got {fwhm!r}")
    if not pixel_scale > 0:
        raise ValueError(f"pixel_scale must be > 0 arcsec, got {pixel_scale!r}")
    sigma = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0))) / pixel_scale  # pixels
    if size is None:
        size = 2 * math.ceil(5.0 * sigma) + 1
    if isinstance(size, bool) or not isinstance(size, int) or size < 1 or size % 2 == 0:
        raise ValueError(f"size must be a positive odd integer, got {size!r}")
    i = torch.arange(size, dtype=torch.float64) - size // 2
    if integrate:
        s2 = sigma * math.sqrt(2.0)
        prof = 0.5 * (torch.erf((i + 0.5) / s2) - torch.erf((i - 0.5) / s2))
    else:
        prof = torch.exp(-0.5 * (i / sigma) ** 2)
    k = prof[:, None] * prof[None, :]
    return (k / k.sum()).to(dtype=dtype, device=device)


def psf_fwhm(kernel, pixel_scale: float = PIXEL_SCALE, upsample: int = 8) -> float:
    """Effective FWHM (arcsec) of a centred kernel: 2·√(A/π), A = area above half max.

    The kernel is bilinearly upsampled ``upsample``× first (kernel values are pixel
    integrals, so this measures the pixel-convolved PSF). A diagnostic, not used in
    the simulation.
    """
    k = torch.as_tensor(kernel, dtype=torch.float64)
    up = F.interpolate(k[None, None], scale_factor=upsample, mode="bilinear", align_corners=False)[
        0, 0
    ]
    area = (up >= 0.5 * up.max()).sum().item() * (pixel_scale / upsample) ** 2
    return 2.0 * math.sqrt(area / math.pi)


# ---------------------------------------------------------------------- convolution


def fft_size(n: int) -> int:
    """Smallest ``2^a·3^b ≥ n``: an FFT length that pocketfft and cuFFT transform fast
    (the linear convolution of ``h`` and ``k`` pixels needs ``≥ h + k − 1``; 124 → 128
    takes a third of the time on one CPU core)."""
    if n < 1:
        raise ValueError(f"n = {n!r} must be >= 1")
    best = 1 << (n - 1).bit_length()
    p3 = 1
    while p3 < best:
        p2 = p3
        while p2 < n:
            p2 *= 2
        best = min(best, p2)
        p3 *= 3
    return best


@dataclass(frozen=True)
class KernelSpectrum:
    """The real FFT of a PSF kernel zero-padded to ``shape`` (:func:`kernel_spectrum`),
    for images of ``image_shape``; reused by every image that :func:`convolve` gets it for."""

    spectrum: torch.Tensor
    shape: tuple[int, int]
    kernel_shape: tuple[int, int]
    image_shape: tuple[int, int]


def kernel_spectrum(kernel: torch.Tensor, image_shape: tuple[int, int]) -> KernelSpectrum:
    """The spectrum of ``kernel`` for the FFT convolution of ``image_shape`` images
    (padded to :func:`fft_size` of ``h + k_h − 1`` per axis)."""
    kernel = torch.as_tensor(kernel)
    _check_kernel(kernel)
    kh, kw = kernel.shape
    h, w = (int(v) for v in image_shape)
    shape = (fft_size(h + kh - 1), fft_size(w + kw - 1))
    return KernelSpectrum(torch.fft.rfft2(kernel, s=shape), shape, (kh, kw), (h, w))


def _check_kernel(kernel: torch.Tensor) -> None:
    if kernel.ndim != 2 or kernel.shape[0] % 2 == 0 or kernel.shape[1] % 2 == 0:
        raise ValueError(f"kernel must be 2-D with odd sides, got shape {tuple(kernel.shape)}")


def convolution_method(method: str, kernel_shape: tuple[int, int], device) -> str:
    """The method :func:`convolve` uses: ``'auto'`` resolved to 'fft' on CPU, else to
    'direct' for kernels up to ``DIRECT_MAX_KERNEL`` pixels per side."""
    if method not in ("auto", "direct", "fft"):
        raise ValueError(f"method must be 'auto', 'direct' or 'fft', got {method!r}")
    if method != "auto":
        return method
    small = max(kernel_shape) <= DIRECT_MAX_KERNEL
    return "direct" if (small and torch.device(device).type != "cpu") else "fft"


def convolve(
    images: torch.Tensor,
    kernel: torch.Tensor,
    method: str = "auto",
    *,
    spectrum: KernelSpectrum | None = None,
) -> torch.Tensor:
    """Convolve ``images`` (..., H, W) with a 2-D odd ``kernel``; 'same' size, zero padding.

    ``method``: 'direct' (``conv2d``), 'fft' (``torch.fft``, padded to
    :func:`fft_size`) or 'auto' (FFT on CPU; elsewhere direct when the kernel side is
    ≤ ``DIRECT_MAX_KERNEL``). The kernel follows the images' dtype/device.
    ``spectrum``: the kernel's :func:`kernel_spectrum` for these images (same dtype and
    device), so that a renderer transforms its PSF once, not once per image.
    """
    if images.ndim < 2:
        raise ValueError(f"images must have at least 2 dimensions, got shape {tuple(images.shape)}")
    kernel = torch.as_tensor(kernel).to(dtype=images.dtype, device=images.device)
    _check_kernel(kernel)
    kh, kw = kernel.shape
    method = convolution_method(method, (kh, kw), images.device)
    h, w = images.shape[-2:]
    lead = images.shape[:-2]
    x = images.reshape(-1, 1, h, w)
    if method == "direct":
        weight = torch.flip(kernel, (0, 1))[None, None]
        out = F.conv2d(x, weight, padding=(kh // 2, kw // 2))
    else:
        if spectrum is None:
            spectrum = kernel_spectrum(kernel, (h, w))
        elif spectrum.kernel_shape != (kh, kw) or spectrum.image_shape != (h, w):
            raise ValueError(
                f"spectrum is for a {spectrum.kernel_shape} kernel and {spectrum.image_shape} "
                f"images, got {(kh, kw)} and {(h, w)}"
            )
        fh, fw = spectrum.shape
        full = torch.fft.irfft2(torch.fft.rfft2(x, s=(fh, fw)) * spectrum.spectrum, s=(fh, fw))
        out = full[..., kh // 2 : kh // 2 + h, kw // 2 : kw // 2 + w]
    return out.reshape(*lead, h, w)


# ---------------------------------------------------------------------------- noise


@dataclass(frozen=True)
class Instrument:
    """HST ACS/WFC F814W settings of docs/physics.md (lenstronomy ``SingleBand`` names).

    exposure_time : s per exposure; ccd_gain : e⁻/ADU (only for ADU conversion);
    read_noise : e⁻ per exposure; sky_brightness : mag/arcsec²; magnitude_zero_point :
    mag for 1 e⁻/s; pixel_scale : arcsec; psf_fwhm : arcsec (Gaussian fallback only);
    noise_correlation : lag-1 correlation of neighbouring pixels' noise along each axis
    (:func:`correlate_noise`; 0 = independent pixels), or a range ``(low, high)``: then
    each :func:`add_noise` call draws it uniformly, after its noise, from its own
    generator (so an image's correlation follows from its noise seed, and its noise
    field is the one a fixed correlation would filter).
    """

    exposure_time: float = 2200.0
    ccd_gain: float = 1.58
    read_noise: float = 3.0
    sky_brightness: float = 21.83
    magnitude_zero_point: float = ZERO_POINT
    num_exposures: int = 1
    pixel_scale: float = PIXEL_SCALE
    psf_fwhm: float = 0.1
    noise_correlation: float | tuple[float, float] = 0.0

    def __post_init__(self) -> None:
        for name in ("exposure_time", "ccd_gain", "pixel_scale", "psf_fwhm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        if not self.read_noise >= 0:
            raise ValueError(f"read_noise must be >= 0 e-, got {self.read_noise!r}")
        rho = self.noise_correlation
        bounds = tuple(rho) if isinstance(rho, (tuple, list)) else (rho,)
        if not (
            len(bounds) in (1, 2)
            and all(isinstance(b, (int, float)) and 0 <= b < MAX_NOISE_CORRELATION for b in bounds)
            and bounds[0] <= bounds[-1]
        ):
            raise ValueError(
                f"noise_correlation must be a number in [0, {MAX_NOISE_CORRELATION:.4f}) "
                f"(lag-1 correlation of a 3-tap kernel) or a range [low, high] of two such "
                f"numbers with low <= high, got {rho!r}"
            )
        if len(bounds) == 2:
            object.__setattr__(self, "noise_correlation", tuple(float(b) for b in bounds))
        if (
            isinstance(self.num_exposures, bool)
            or not isinstance(self.num_exposures, int)
            or self.num_exposures < 1
        ):
            raise ValueError(
                f"num_exposures must be a positive integer, got {self.num_exposures!r}"
            )

    @property
    def total_exposure_time(self) -> float:
        """t·N_exp, s."""
        return self.exposure_time * self.num_exposures

    @property
    def sky_per_pixel(self) -> float:
        """Sky level, e⁻/s per pixel."""
        return (
            10.0 ** (-0.4 * (self.sky_brightness - self.magnitude_zero_point)) * self.pixel_scale**2
        )

    @property
    def background_sigma(self) -> float:
        """σ of an empty (sky-subtracted) pixel, e⁻/s (lenstronomy ``background_noise``)."""
        t = self.total_exposure_time
        return math.sqrt(self.sky_per_pixel * t + self.num_exposures * self.read_noise**2) / t

    def noise_sigma_map(self, image: torch.Tensor) -> torch.Tensor:
        return noise_sigma_map(image, self)

    def add_noise(
        self, image: torch.Tensor, generator=None, *, poisson: str = "exact"
    ) -> torch.Tensor:
        return add_noise(image, generator, instrument=self, poisson=poisson)


def noise_sigma_map(image: torch.Tensor, instrument: Instrument | None = None) -> torch.Tensor:
    """Per-pixel noise σ (e⁻/s) of a noise-free ``image`` in e⁻/s per pixel."""
    inst = instrument or Instrument()
    image = torch.as_tensor(image)
    t = inst.total_exposure_time
    var_counts = (
        image.clamp(min=0.0) * t + inst.sky_per_pixel * t + inst.num_exposures * inst.read_noise**2
    )
    return torch.sqrt(var_counts) / t


def _generator(generator, device: torch.device) -> torch.Generator | None:
    if generator is None or isinstance(generator, torch.Generator):
        return generator
    if isinstance(generator, (int, np.integer)) and not isinstance(generator, bool):
        g = torch.Generator(device=device)
        g.manual_seed(int(generator))
        return g
    raise ValueError(f"generator must be a torch.Generator, an int seed or None, got {generator!r}")


def add_noise(
    image: torch.Tensor,
    generator: torch.Generator | int | None = None,
    *,
    instrument: Instrument | None = None,
    poisson: str = "exact",
) -> torch.Tensor:
    """Noisy copy of ``image`` (e⁻/s per pixel, any shape).

    ``generator``: a ``torch.Generator`` on the image's device, an int seed (a fresh
    generator on that device), or None (global RNG). ``poisson``: 'exact'
    (``torch.poisson`` on electron counts) or 'gaussian' (normal approximation). The
    noise of neighbouring pixels is correlated by the instrument's ``noise_correlation``
    (:func:`correlate_noise` along the last two axes; a range draws one value per call
    after the noise). Same seed, device and dtype → identical result.
    """
    if poisson not in ("exact", "gaussian"):
        raise ValueError(f"poisson must be 'exact' or 'gaussian', got {poisson!r}")
    inst = instrument or Instrument()
    image = torch.as_tensor(image)
    g = _generator(generator, image.device)
    t = inst.total_exposure_time
    if poisson == "gaussian":
        z = torch.randn(image.shape, generator=g, dtype=image.dtype, device=image.device)
        noise = noise_sigma_map(image, inst) * z
        return image + correlate_noise(noise, _correlation(inst, g, image.device))
    # torch.poisson draws in the rate's dtype; use float64 so counts ≫ 2^24 stay exact
    lam = ((image.clamp(min=0.0) + inst.sky_per_pixel) * t).to(torch.float64)
    shot = torch.poisson(lam, generator=g) - lam
    z = torch.randn(image.shape, generator=g, dtype=torch.float64, device=image.device)
    read = math.sqrt(inst.num_exposures) * inst.read_noise * z
    rho = _correlation(inst, g, image.device)
    return image + correlate_noise((shot + read) / t, rho).to(image.dtype)


def _correlation(inst: Instrument, generator, device) -> float:
    """The instrument's noise correlation, drawn from ``generator`` when it is a range."""
    rho = inst.noise_correlation
    if not isinstance(rho, tuple):
        return float(rho)
    u = torch.rand((), generator=generator, dtype=torch.float64, device=device)
    return rho[0] + (rho[1] - rho[0]) * float(u)


#: Largest lag-1 correlation of the 3-tap kernel ``(w, 1, w)``: 1/√2, at w = 1/√2.
MAX_NOISE_CORRELATION = 1.0 / math.sqrt(2.0)


def noise_kernel_weight(rho: float) -> float:
    """Side weight ``w`` of the kernel ``(w, 1, w)`` whose lag-1 correlation
    ``2w / (1 + 2w²)`` is ``rho`` (the root with w ≤ 1/√2): ``(1 − √(1 − 2ρ²)) / (2ρ)``."""
    if not 0 <= rho < MAX_NOISE_CORRELATION:
        raise ValueError(f"noise correlation must be in [0, 1/sqrt(2)), got {rho!r}")
    return 0.0 if rho == 0 else (1.0 - math.sqrt(1.0 - 2.0 * rho * rho)) / (2.0 * rho)


def correlate_noise(noise: torch.Tensor, rho: float) -> torch.Tensor:
    """Independent pixel noise ``(..., H, W)`` made correlated like a drizzled image's.

    Filters both pixel axes with ``(w, 1, w)/√(1 + 2w²)``, ``w`` from
    :func:`noise_kernel_weight`: every pixel keeps its variance (at the border the
    missing tap is dropped and the other two renormalised), neighbours along an axis
    correlate by ``rho``, diagonal neighbours by ``rho²``, pixels two apart by
    ``w²/(1 + 2w²)``. ``rho = 0`` returns ``noise`` itself.
    """
    if rho == 0:
        return noise
    w = noise_kernel_weight(rho)
    for dim in (noise.ndim - 1, noise.ndim - 2):
        n = noise.shape[dim]
        pad = torch.zeros_like(noise.narrow(dim, 0, 1))
        left = torch.cat([pad, noise.narrow(dim, 0, n - 1)], dim)
        right = torch.cat([noise.narrow(dim, 1, n - 1), pad], dim)
        idx = torch.arange(n, device=noise.device)
        taps = 2 - (idx == 0).to(noise.dtype) - (idx == n - 1).to(noise.dtype)
        shape = [1] * noise.ndim
        shape[dim] = n
        noise = (noise + w * (left + right)) * torch.rsqrt(1.0 + w * w * taps).reshape(shape)
    return noise
