"""Batched, noise-free renderer of lens images (SCIENCE.md §2-§5).

Pipeline for a batch of ``B`` systems (``docs/_simulation_render.md``):

1. coordinates: the ``(npix·k)²`` sub-pixel grid (``k = supersample``) plus, when
   ``k > 1``, the ``npix²`` pixel centres (needed for the negative sheets);
2. lens equation: main-lens EPL (amplitude θ_E^(γ−1)) + external shear (about the
   origin) + m = 3, 4 multipoles (about the lens centre) + the subhalo population and
   its negative sheet, all in the lens plane; with line-of-sight halos, one extra plane
   per slice redshift (own negative sheet) and :func:`subslope.raytrace.multi_plane_ray_shoot`;
3. source surface brightness at β (COSMOS stamps via :mod:`subslope.light.pixelated`, or
   an elliptical Sérsic rotated by ``src_rotation``, or a multi-Sérsic source: a sum of
   Sérsic components whose shapes and centre offsets rotate with ``src_rotation``),
   plus the unlensed Sérsic lens light;
4. binning of the k×k sub-pixels, × pixel area (e⁻/s per pixel), PSF convolution
   (:func:`subslope.instrument.convolve`, one image at a time).

Negative sheets: ``κ_sheet = −(1/P) Σ_pixels Σ_members κ_i`` with the member
convergences taken at the pixel-centre rays *on that plane* (for the main-lens plane of
a single-plane scene: the pixel centres themselves); the sheet deflection is
``κ_sheet·(x, y)`` about the plane's origin. The summed convergence comes out of the
same fused pass as the deflections (one extra multiply), so the sheet costs no second
pass over the population.

Components whose macro keys are absent (or populations that are empty) are not
evaluated at all. Every evaluated stage increments :data:`STAGE_COUNTS` (a
:class:`collections.Counter`, reset with :func:`reset_stage_counts`), and the stage
functions are called through this module's globals, so tests can also monkeypatch them.

Population passes (subhalos, LoS halos) run on member tables and fused pair kernels
(:mod:`subslope.pair_kernels`, ``torch.compile``'d on CPU); large populations use the
near/far split of :mod:`subslope.nearfar` (``RenderSettings.population``).

Determinism: on CPU the images of a batch are rendered one at a time, so image ``i``
alone == image ``i`` in a batch, bit for bit (all member counts, chunk widths and
split radii are per image). On other devices images are rendered in sub-batches
padded to the largest population: there an image alone and in a batch agree to float
rounding (member sums are compiled reductions whose order may depend on the padded
width); inactive planes are exact no-ops and the PSF is applied image by image.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from subslope.grid import pixel_grid
from subslope.instrument import convolve
from subslope.light.pixelated import pixelated_light
from subslope.light.sersic import multi_sersic_from_magnitude, sersic_ellipse_from_magnitude
from subslope.population import pack_ragged
from subslope.profiles.epl import theta_e_to_amp
from subslope.nearfar import GridBlock, split_pass
from subslope.pair_kernels import (circle_peaks, direct_sums, direct_sums_few, epl_table, far_sums,
                                   few_sums_with_sheet, member_table, near_tile_sums)
from subslope.profiles.multipole import multipole_deflection
from subslope.profiles.shear import shear_deflection
from subslope.raytrace import Plane, multi_plane_ray_shoot

__all__ = [
    "RenderSettings",
    "PixelatedSources",
    "STAGE_COUNTS",
    "reset_stage_counts",
    "render_smooth",
    "render",
    "chunk_width",
]

log = logging.getLogger(__name__)

#: On CPU render the images of a batch one at a time (True, the default). Tests set it
#: to False to exercise the sub-batched (accelerator) code path on CPU.
_PER_IMAGE_ON_CPU = True

#: Stages evaluated since the last :func:`reset_stage_counts` (one count per
#: sub-batch that ran the stage): ``main_lens``, ``shear``, ``multipoles``,
#: ``subhalos`` (population pass incl. its sheet), ``los`` (one per LoS plane copy),
#: ``multi_plane``, ``single_plane``, ``lens_light``, ``source_sersic``,
#: ``source_multi_sersic`` (plus ``source_component``, one count per multi-Sérsic
#: component evaluated), ``source_pixelated``, ``supersample_bin``, ``psf``.
STAGE_COUNTS: Counter = Counter()


def reset_stage_counts() -> None:
    """Clear :data:`STAGE_COUNTS`."""
    STAGE_COUNTS.clear()


def _stage(name: str) -> None:
    STAGE_COUNTS[name] += 1


# ----------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class RenderSettings:
    """Knobs of the renderer (defaults measured in ``docs/_simulation_render.md``).

    npix, pixel_scale : image size (pixels) and pixel size (arcsec).
    supersample : sub-pixels per pixel side k (surface brightness averaged over k×k).
    dtype, device : torch dtype; device None → 'cuda' if available else 'cpu' (at call time).
    n_terms : hypergeometric-series terms of the subhalo / LoS EPL deflections.
    n_terms_main : series terms of the main-lens EPL.
    max_elements : memory budget: members × points of one kernel call (a (b, N, P)
        intermediate in eager mode); sets the sub-batch size off-CPU and the auto
        chunk width.
    chunk_members : members per direct kernel call (rounded down to a power of two);
        None → :func:`chunk_width` (from ``max_elements`` and P only, never from B).
    population : 'auto' | 'split' | 'direct': how a population's deflection is summed.
        'direct' evaluates every member at every point; 'split' uses the near/far
        split of :mod:`subslope.nearfar` (exact near field within each member's radius
        r_c, far field interpolated from a node mesh); 'auto' = 'split' for
        populations of at least ``split_min_members`` members on a plane, else 'direct'.
    split_spacing : node spacing h of the far-field mesh, in pixels.
    split_order : Lagrange interpolation points per axis of the far field (4, 6, 8).
    split_tolerance : far-field interpolation error allowed per member (arcsec) in a
        population of ≤ 1000 members, ∝ 1/N above; sets each member's r_c
        (:func:`subslope.nearfar.member_rungs`).
    split_min_members : smallest population that 'auto' splits.
    source_interpolation : 'bilinear' | 'bicubic' | 'nearest' for pixelated sources.
    convolution : 'auto' | 'direct' | 'fft' (:func:`subslope.instrument.convolve`).
    zero_point : AB magnitude of 1 e⁻/s.
    compile : 'auto' (torch.compile the EPL chunk kernel on CPU when a C compiler is
        found, eager on failure), 'on' (same, also off-CPU), 'off' (eager).
    """

    npix: int = 100
    pixel_scale: float = 0.04
    supersample: int = 1
    dtype: torch.dtype = torch.float32
    device: str | None = None
    n_terms: int = 8
    n_terms_main: int = 14
    max_elements: int = 2**22
    source_interpolation: str = "bilinear"
    convolution: str = "auto"
    zero_point: float = 25.127
    chunk_members: int | None = None
    compile: str = "auto"
    population: str = "auto"
    split_spacing: int = 2
    split_order: int = 6
    split_tolerance: float = 2e-5
    split_min_members: int = 64

    def __post_init__(self) -> None:
        for name in ("npix", "supersample", "n_terms", "n_terms_main", "max_elements"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"RenderSettings.{name} must be a positive int, got {v!r}")
        if not self.pixel_scale > 0:
            raise ValueError(f"RenderSettings.pixel_scale must be > 0 arcsec, got {self.pixel_scale!r}")
        if self.chunk_members is not None and (not isinstance(self.chunk_members, int) or self.chunk_members < 1):
            raise ValueError(f"RenderSettings.chunk_members must be None or an int >= 1, got {self.chunk_members!r}")
        if self.compile not in ("auto", "on", "off"):
            raise ValueError(f"RenderSettings.compile must be 'auto', 'on' or 'off', got {self.compile!r}")
        if self.source_interpolation not in ("bilinear", "bicubic", "nearest"):
            raise ValueError("RenderSettings.source_interpolation must be 'bilinear', 'bicubic' or "
                             f"'nearest', got {self.source_interpolation!r}")
        if self.convolution not in ("auto", "direct", "fft"):
            raise ValueError(f"RenderSettings.convolution must be 'auto', 'direct' or 'fft', got {self.convolution!r}")
        if self.population not in ("auto", "split", "direct"):
            raise ValueError(f"RenderSettings.population must be 'auto', 'split' or 'direct', got {self.population!r}")
        if not (isinstance(self.split_tolerance, (int, float)) and self.split_tolerance > 0):
            raise ValueError(f"RenderSettings.split_tolerance must be > 0 arcsec, got {self.split_tolerance!r}")
        if self.split_order not in (4, 6, 8):
            raise ValueError(f"RenderSettings.split_order must be 4, 6 or 8, got {self.split_order!r}")
        for name, lo, hi in (("split_spacing", 1, 64), ("split_min_members", 1, 1 << 30)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"RenderSettings.{name} must be an int in [{lo}, {hi}], got {v!r}")
        if not self.dtype.is_floating_point:
            raise ValueError(f"RenderSettings.dtype must be a floating dtype, got {self.dtype}")


@dataclass
class PixelatedSources:
    """Pixelated sources of a batch (see :func:`subslope.light.pixelated.pad_stamps`).

    stamps : (B, H, W) surface brightness at z_source, e⁻/s per arcsec².
    pixel_scale : (B,) stamp pixel size at z_source, arcsec.
    offsets : (B, 2) (offset_x, offset_y) in stamp pixels from ``pad_stamps``.
    """

    stamps: np.ndarray | Tensor
    pixel_scale: np.ndarray
    offsets: np.ndarray | Tensor


def _pow2_floor(n: int) -> int:
    return 1 << (max(1, int(n)).bit_length() - 1)



def chunk_width(settings: RenderSettings, n_points: int, compiled: bool = True) -> int:
    """Members per direct kernel call: ``chunk_members``, or the largest power of two
    ≤ ``max_elements / P`` (compiled kernels: no (N, P) intermediate is stored) or
    ≤ ``max_elements / (32·P)`` (eager: about 32 live intermediates), clamped to
    [1, 4096]. A function of the settings and the number of points only (batch
    invariance)."""
    if settings.chunk_members is not None:
        return _pow2_floor(settings.chunk_members)
    per = max(1, n_points) * (1 if compiled else 32)
    return max(1, min(4096, _pow2_floor(settings.max_elements // per)))


# ----------------------------------------------------------------------------- kernels
_COMPILED: dict[Any, Any] = {}
_COMPILE_FAILED: set = set()
_MAX_KERNEL_GRAPHS = 64
_KERNEL_FUNCTIONS = {"direct": direct_sums, "few": direct_sums_few, "few_sheet": few_sums_with_sheet,
                     "far": far_sums, "near": near_tile_sums, "peaks": circle_peaks}
#: Populations of fewer members than this are summed by ``direct_sums_few`` (members
#: on the outer axis) instead of ``direct_sums`` (members vectorised).
FEW_MEMBERS = 32


@dataclass(frozen=True)
class _Kernels:
    """The population kernels of one render call (compiled or eager)."""

    direct: Any
    few: Any
    few_sheet: Any
    far: Any
    near: Any
    peaks: Any
    compiled: bool


def _compiled_or_eager(name: str, device: torch.device):
    fn = _KERNEL_FUNCTIONS[name]
    key = (device.type, name)
    if key in _COMPILE_FAILED:
        return fn
    if key not in _COMPILED:
        # dynamic shapes: one graph per (profile, table rows, dtype), whatever the
        # member and point counts; dynamo's default of 8 graphs per function would
        # silently fall back to eager in a process that renders many settings.
        dynamo_config = torch._dynamo.config
        dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, _MAX_KERNEL_GRAPHS)
        _COMPILED[key] = torch.compile(fn, dynamic=True, fullgraph=True)
    compiled = _COMPILED[key]

    def run(*args):
        if key in _COMPILE_FAILED:
            return fn(*args)
        try:
            return compiled(*args)
        except Exception as exc:  # pragma: no cover - depends on the toolchain
            log.warning("torch.compile of the %s population kernel failed (%s); using eager", name, exc)
            _COMPILE_FAILED.add(key)
            return fn(*args)

    return run


def _kernels(settings: RenderSettings, device: torch.device) -> _Kernels:
    """Population kernels: torch.compile'd (``compile`` 'on', or 'auto' on a CPU with a
    C compiler) or eager (:mod:`subslope.pair_kernels`)."""
    want = settings.compile == "on" or (settings.compile == "auto" and device.type == "cpu")
    if want and device.type == "cpu" and shutil.which("gcc") is None and shutil.which("cc") is None:
        want = False
    if not want:
        return _Kernels(direct_sums, direct_sums_few, few_sums_with_sheet, far_sums, near_tile_sums, circle_peaks,
                        False)
    return _Kernels(*(_compiled_or_eager(n, device) for n in ("direct", "few", "few_sheet", "far", "near", "peaks")),
                    True)


# --------------------------------------------------------------------------- populations
def _select_systems(counts, idx) -> tuple[np.ndarray, np.ndarray]:
    """Counts of systems ``idx`` of a ragged population and the flat indices of their members."""
    counts_all = np.asarray(counts, dtype=np.int64)
    off = np.concatenate([[0], np.cumsum(counts_all)])
    sel = np.concatenate([np.arange(off[i], off[i + 1]) for i in idx]) if len(idx) else np.zeros(0, np.int64)
    return counts_all[idx], sel


_PAD = {"amp": 0.0, "gamma": 2.0, "e1": 0.0, "e2": 0.0, "x": 0.0, "y": 0.0,
        "r_s": 1.0, "alpha_rs": 0.0, "r_t": 1.0}
_PROFILE_KEYS = {"epl": ("amp", "gamma", "e1", "e2", "x", "y"),
                 "nfw": ("r_s", "alpha_rs", "x", "y"),
                 "tnfw": ("r_s", "alpha_rs", "r_t", "x", "y")}


@dataclass
class _Pop:
    """A padded population of a sub-batch: its member table ``(b, M, N)``
    (:func:`subslope.pair_kernels.member_table`; padded members have zero amplitude)."""

    profile: str
    table: Tensor
    counts: np.ndarray


def _profile_values(profile: str, flat: dict[str, np.ndarray]):
    """``(key, float64 values)`` of every parameter of ``profile``; a clear error for a
    missing one."""
    for key in _PROFILE_KEYS[profile]:
        if flat.get(key) is None:
            raise ValueError(f"population of profile {profile!r} has no {key!r} values")
        yield key, np.asarray(flat[key], dtype=np.float64)


def _pack(profile: str, flat: dict[str, np.ndarray], counts: np.ndarray, n_terms: int, dtype, device) -> _Pop:
    n_pad = max(1, int(counts.max()) if counts.size else 0)
    params = {}
    for key, vals in _profile_values(profile, flat):
        arr, _ = pack_ragged(vals, counts=counts, n_max=n_pad, fill=_PAD[key])
        params[key] = torch.as_tensor(arr, dtype=dtype, device=device)
    return _Pop(profile, member_table(profile, params, n_terms), counts)


def _flat_table(profile: str, flat: dict[str, np.ndarray], n_terms: int, dtype, device) -> Tensor:
    """Member table ``(M, n + 1)`` of ``n`` members given as flat arrays, plus one padding
    member (zero amplitude) as the last column."""
    params = {key: torch.as_tensor(np.append(vals, _PAD[key]), dtype=dtype, device=device)[None, :]
              for key, vals in _profile_values(profile, flat)}
    return member_table(profile, params, n_terms)[0]


@dataclass(frozen=True)
class _Geometry:
    """Layout of the points of a render call: regular grid blocks (sub-pixels, then
    pixel centres when supersampled), the block of pixel centres, the undeflected
    grid ``(1, P)`` and whether the rays on this plane are displaced from it."""

    blocks: tuple[GridBlock, ...]
    sheet_block: int
    base: tuple[Tensor, Tensor]
    displaced: bool = True


def _use_split(pop: _Pop, settings: RenderSettings, geometry: _Geometry | None) -> bool:
    if geometry is None or settings.population == "direct":
        return False
    return settings.population == "split" or int(pop.counts.max()) >= settings.split_min_members


def _population_pass(pop: _Pop, x: Tensor, y: Tensor, settings: RenderSettings, kernels: _Kernels,
                     n_pix: int, geometry: _Geometry | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Summed deflection at (x, y) ``(b, P_all)`` and the negative-sheet κ ``(b, 1)``
    (minus the mean summed κ over the last ``n_pix`` points, the pixel-centre rays).

    With ``geometry`` and a population large enough (``settings.population``), the
    near/far split of :mod:`subslope.nearfar`; otherwise the direct sum in chunks of
    :func:`chunk_width` members.
    """
    n_all = x.shape[-1]
    if _use_split(pop, settings, geometry):
        _stage("split")
        out = split_pass(pop.table, pop.profile, x, y, list(geometry.blocks), geometry.sheet_block,
                         spacing=settings.split_spacing * settings.pixel_scale, order=settings.split_order,
                         tolerance=settings.split_tolerance, displaced=geometry.displaced, base=geometry.base,
                         kernels=(kernels.far, kernels.near, kernels.peaks), max_elements=settings.max_elements)
        ax, ay, k_sum = out
        k_sheet = -(k_sum / n_pix)[:, None]
        return ax + k_sheet * x, ay + k_sheet * y, k_sheet
    n = pop.table.shape[-1]
    if n < FEW_MEMBERS and kernels.compiled:
        return kernels.few_sheet(x, y, pop.table, pop.profile, n_pix)
    w = chunk_width(settings, n_all, kernels.compiled)
    ax = ay = kap = None
    for start in range(0, n, w):
        dax, day, dk = kernels.direct(x, y, pop.table[:, :, start:start + w].contiguous(), pop.profile, True)
        if ax is None:
            ax, ay, kap = dax, day, dk
        else:
            ax, ay, kap = ax + dax, ay + day, kap + dk
    k_sheet = -(kap[:, n_all - n_pix:].sum(-1) / n_pix)[:, None]
    return ax + k_sheet * x, ay + k_sheet * y, k_sheet


def _main_lens_deflection(x: Tensor, y: Tensor, table: Tensor, kernels: _Kernels) -> tuple[Tensor, Tensor]:
    """Main-lens EPL deflection ``(b, P)`` from its one-member table ``(b, M, 1)``
    (``n_terms_main`` series terms; the same arithmetic as
    :func:`subslope.profiles.epl.epl_deflection`, as one fused kernel)."""
    ax, ay, _ = kernels.few(x, y, table, "epl", False)
    return ax, ay


# ------------------------------------------------------------------------------ helpers
def _resolve_device(settings: RenderSettings) -> torch.device:
    if settings.device is not None:
        return torch.device(settings.device)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


_REQUIRED = ("z_lens", "z_source", "lens_x", "lens_y", "theta_e", "lens_e1", "lens_e2", "gamma_ml",
             "src_x", "src_y", "src_rotation")
_GROUPS = {"multipoles": ("a3", "phi3", "a4", "phi4"), "shear": ("shear_g1", "shear_g2"),
           "lens_light": ("light_mag", "light_r", "light_n", "light_e1", "light_e2"),
           "source_sersic": ("src_mag", "src_r", "src_n", "src_e1", "src_e2")}


def _multi_sersic_slots(macro: dict) -> int:
    """Number K of multi-Sérsic component slots in ``macro`` (0: not a multi-Sérsic source)."""
    if "src_ncomp" not in macro:
        return 0
    k = 0
    while f"src_frac_{k}" in macro:
        k += 1
    return k


_MULTI_PER = ("frac", "r", "n", "e1", "e2", "dx", "dy")


def _check_macro(macro: dict, sources) -> int:
    missing = [k for k in _REQUIRED if k not in macro]
    if missing:
        raise ValueError(f"macro is missing keys {missing} (see subslope.scenes.sample_macro)")
    n = len(np.asarray(macro["z_lens"]))
    for k, v in macro.items():
        if np.ndim(v) != 1 or len(v) != n:
            raise ValueError(f"macro[{k!r}] must be 1-D of length B = {n}, got shape {np.shape(v)}")
    for g, keys in _GROUPS.items():
        have = [k in macro for k in keys]
        if any(have) and not all(have):
            raise ValueError(f"macro has only some of the {g} keys {keys}: give all or none")
    kmax = _multi_sersic_slots(macro)
    if "src_ncomp" in macro or "src_mag_total" in macro:
        need = ["src_mag_total", "src_ncomp"] + [f"src_{p}_{j}" for j in range(max(kmax, 1)) for p in _MULTI_PER]
        missing = [kk for kk in need if kk not in macro]
        if missing:
            raise ValueError(f"multi-Sérsic source keys {missing} are missing from macro "
                             "(see subslope.scenes.multi_sersic_keys)")
        if "src_mag" in macro or sources is not None:
            raise ValueError("give exactly one source: multi-Sérsic keys (src_mag_total, src_ncomp, ...), "
                             "Sérsic keys (src_mag, ...) or sources=")
        return n
    sersic = "src_mag" in macro
    if sersic and sources is not None:
        raise ValueError("give either Sérsic source keys (src_mag, ...) in macro or sources=, not both")
    if not sersic and sources is None:
        raise ValueError("no source: pass sources=PixelatedSources(...) or Sérsic keys src_mag, src_r, "
                         "src_n, src_e1, src_e2 in macro")
    return n


def _has(macro: dict, group: str) -> bool:
    return _GROUPS[group][0] in macro


def _bin(img: Tensor, k: int) -> Tensor:
    """Mean of k×k blocks as a fixed sum of strided slices (element-wise, deterministic)."""
    if k == 1:
        return img
    b, hk, wk = img.shape
    v = img.reshape(b, hk // k, k, wk // k, k)
    acc = None
    for i in range(k):
        for j in range(k):
            s = v[:, :, i, :, j]
            acc = s if acc is None else acc + s
    return acc * (1.0 / (k * k))


# ------------------------------------------------------------------------------- render
def _render_group(idx: np.ndarray, macro: dict, psf: Tensor, settings: RenderSettings,
                  sources: PixelatedSources | None, subhalos, los, smooth: bool,
                  grid: tuple[Tensor, Tensor, int], device, kernels: _Kernels,
                  geometry: _Geometry) -> Tensor:
    dtype = settings.dtype
    k = settings.supersample
    xg, yg, n_pix = grid
    b = idx.size

    def par(key: str) -> Tensor:
        return torch.as_tensor(np.asarray(macro[key], dtype=np.float64)[idx], dtype=dtype,
                               device=device)[:, None]

    zl = np.asarray(macro["z_lens"], dtype=np.float64)[idx]
    zs = np.asarray(macro["z_source"], dtype=np.float64)[idx]

    # lens-plane populations of this sub-batch
    sub_pop = None
    if not smooth and subhalos is not None:
        counts, sel = _select_systems(subhalos.counts, idx)
        if counts.sum() > 0:
            flat = {kk: (None if getattr(subhalos, kk, None) is None else np.asarray(getattr(subhalos, kk))[sel])
                    for kk in _PROFILE_KEYS[subhalos.profile]}
            sub_pop = _pack(subhalos.profile, flat, counts, settings.n_terms, dtype, device)

    lens_amp = theta_e_to_amp(par("theta_e"), par("gamma_ml"))
    lens = {kk: par(kk) for kk in ("gamma_ml", "lens_e1", "lens_e2", "lens_x", "lens_y")}
    lens_table = epl_table({"amp": lens_amp, "gamma": lens["gamma_ml"], "e1": lens["lens_e1"],
                            "e2": lens["lens_e2"], "x": lens["lens_x"], "y": lens["lens_y"]},
                           settings.n_terms_main).contiguous()
    shear = {kk: par(kk) for kk in _GROUPS["shear"]} if _has(macro, "shear") else None
    mpole = {kk: par(kk) for kk in _GROUPS["multipoles"]} if _has(macro, "multipoles") else None

    def lens_plane(tx: Tensor, ty: Tensor, displaced: bool = True) -> tuple[Tensor, Tensor]:
        _stage("main_lens")
        ax, ay = _main_lens_deflection(tx, ty, lens_table, kernels)
        if shear is not None:
            _stage("shear")
            sx, sy = shear_deflection(tx, ty, shear["shear_g1"], shear["shear_g2"])
            ax, ay = ax + sx, ay + sy
        if mpole is not None:
            _stage("multipoles")
            for m, a, phi in ((3, "a3", "phi3"), (4, "a4", "phi4")):
                mx, my = multipole_deflection(tx, ty, m, mpole[a], mpole[phi], lens["lens_x"], lens["lens_y"])
                ax, ay = ax + mx, ay + my
        if sub_pop is not None:
            _stage("subhalos")
            geo = geometry if displaced else dataclasses.replace(geometry, displaced=False)
            px, py, _ = _population_pass(sub_pop, tx, ty, settings, kernels, n_pix, geo)
            ax, ay = ax + px, ay + py
        return ax, ay

    # line-of-sight planes
    planes: list[Plane] = []
    if not smooth and los is not None:
        counts, sel = _select_systems(los.counts, idx)
        if counts.sum() > 0:
            sys_local = np.repeat(np.arange(b), counts)
            z_h = np.asarray(los.z, dtype=np.float64)[sel]
            bad = z_h >= zs[sys_local]
            if np.any(bad):
                j = int(np.flatnonzero(bad)[0])
                raise ValueError(f"los.z = {z_h[j]} is not in front of z_source = {zs[sys_local[j]]} "
                                 f"of system {int(idx[sys_local[j]])}")
            front, back = [], []
            flat = {kk: (None if getattr(los, kk, None) is None else np.asarray(getattr(los, kk))[sel])
                    for kk in _PROFILE_KEYS[los.profile]}
            # one member table for every LoS halo of the sub-batch (plus a zero-amplitude
            # column for padding); each slice plane gathers its columns
            table_all = _flat_table(los.profile, flat, settings.n_terms, dtype, device)
            n_los = table_all.shape[-1] - 1
            for zu in np.unique(z_h):
                on = np.flatnonzero(z_h == zu)
                c_slice = np.bincount(sys_local[on], minlength=b)
                cols, _ = pack_ragged(on, counts=c_slice, n_max=max(1, int(c_slice.max())), fill=n_los)
                pop = _Pop(los.profile, table_all[:, torch.as_tensor(cols, device=device)].permute(1, 0, 2),
                           c_slice)
                has = c_slice > 0

                def deflect(tx, ty, pop=pop):
                    _stage("los")
                    ax, ay, _ = _population_pass(pop, tx, ty, settings, kernels, n_pix, geometry)
                    return ax, ay

                a_front, a_back = has & (zu < zl), has & (zu >= zl)
                if a_front.any():
                    front.append(Plane(np.full(b, zu), (deflect,), a_front))
                if a_back.any():
                    back.append(Plane(np.full(b, zu), (deflect,), a_back))
            planes = front + [Plane(zl, (lens_plane,), None)] + back

    if planes:
        _stage("multi_plane")
        bx, by = multi_plane_ray_shoot(xg.expand(b, -1), yg.expand(b, -1), planes, zs)
    else:
        _stage("single_plane")
        ax, ay = lens_plane(xg.expand(b, -1), yg.expand(b, -1), displaced=False)
        bx, by = xg - ax, yg - ay

    n_ss = (settings.npix * k) ** 2
    bx, by = bx[:, :n_ss], by[:, :n_ss]
    kmax = _multi_sersic_slots(macro)
    if kmax:
        _stage("source_multi_sersic")
        rot = par("src_rotation")
        c2, s2 = torch.cos(2 * rot), torch.sin(2 * rot)
        c1, s1 = torch.cos(rot), torch.sin(rot)
        cx, cy = par("src_x"), par("src_y")
        # Components switched off (zero flux for every image of the sub-batch) are skipped.
        active = [j for j in range(kmax) if np.any(np.asarray(macro[f"src_frac_{j}"])[idx] > 0)]
        comp: dict[str, list] = {kk: [] for kk in ("f", "r", "n", "e1", "e2", "x", "y")}
        for j in active:
            _stage("source_component")
            e1, e2 = par(f"src_e1_{j}"), par(f"src_e2_{j}")
            dx, dy = par(f"src_dx_{j}"), par(f"src_dy_{j}")
            comp["f"].append(par(f"src_frac_{j}"))
            comp["r"].append(par(f"src_r_{j}"))
            comp["n"].append(par(f"src_n_{j}"))
            comp["e1"].append(c2 * e1 - s2 * e2)
            comp["e2"].append(s2 * e1 + c2 * e2)
            comp["x"].append(cx + c1 * dx - s1 * dy)
            comp["y"].append(cy + s1 * dx + c1 * dy)
        sb = multi_sersic_from_magnitude(bx, by, par("src_mag_total"), comp["f"], comp["r"], comp["n"],
                                         comp["e1"], comp["e2"], comp["x"], comp["y"],
                                         zero_point=settings.zero_point)
    elif sources is None:
        _stage("source_sersic")
        rot = par("src_rotation")
        e1, e2 = par("src_e1"), par("src_e2")
        c2, s2 = torch.cos(2 * rot), torch.sin(2 * rot)
        sb = sersic_ellipse_from_magnitude(bx, by, par("src_mag"), par("src_r"), par("src_n"),
                                           c2 * e1 - s2 * e2, s2 * e1 + c2 * e2, par("src_x"), par("src_y"),
                                           zero_point=settings.zero_point)
    else:
        _stage("source_pixelated")
        st = torch.as_tensor(sources.stamps)
        st = st[torch.as_tensor(idx, device=st.device)].to(dtype=dtype, device=device)
        offs = torch.as_tensor(sources.offsets)[torch.as_tensor(idx)].to(dtype=dtype, device=device)
        ps = torch.as_tensor(np.asarray(sources.pixel_scale, dtype=np.float64)[idx], dtype=dtype,
                             device=device)[:, None]
        sb = pixelated_light(bx, by, st, ps, par("src_rotation"), par("src_x"), par("src_y"),
                             order=settings.source_interpolation, stamp_offset_x=offs[:, 0:1],
                             stamp_offset_y=offs[:, 1:2])
    if not smooth and _has(macro, "lens_light"):
        _stage("lens_light")
        sb = sb + sersic_ellipse_from_magnitude(
            xg[:, :n_ss], yg[:, :n_ss], par("light_mag"), par("light_r"), par("light_n"), par("light_e1"),
            par("light_e2"), par("lens_x"), par("lens_y"), zero_point=settings.zero_point)
    m = settings.npix * k
    img = sb.reshape(b, m, m)
    if k > 1:
        _stage("supersample_bin")
        img = _bin(img, k)
    img = img * (settings.pixel_scale ** 2)
    _stage("psf")
    return torch.cat([convolve(img[i:i + 1], psf, method=settings.convolution) for i in range(b)], 0)


def _render(macro, psf, settings: RenderSettings, sources, subhalos, los, smooth: bool) -> Tensor:
    if not isinstance(settings, RenderSettings):
        raise ValueError(f"settings must be a RenderSettings, got {type(settings).__name__}")
    n = _check_macro(macro, sources)
    if subhalos is not None and len(subhalos.counts) != n:
        raise ValueError(f"subhalos.counts has {len(subhalos.counts)} systems, macro has {n}")
    if los is not None and len(los.counts) != n:
        raise ValueError(f"los.counts has {len(los.counts)} systems, macro has {n}")
    if subhalos is not None and subhalos.profile not in _PROFILE_KEYS:
        raise ValueError(f"subhalos.profile must be one of {tuple(_PROFILE_KEYS)}, got {subhalos.profile!r}")
    device = _resolve_device(settings)
    dtype = settings.dtype
    psf_t = torch.as_tensor(psf).to(dtype=dtype, device=device)
    k = settings.supersample
    xs, ys = pixel_grid(settings.npix, settings.pixel_scale, k, dtype=dtype, device=device)
    xg, yg = xs.reshape(1, -1), ys.reshape(1, -1)
    n_pix = settings.npix ** 2
    if k > 1:  # append the pixel centres (rays used for the negative sheets)
        xp, yp = pixel_grid(settings.npix, settings.pixel_scale, 1, dtype=dtype, device=device)
        xg = torch.cat([xg, xp.reshape(1, -1)], 1)
        yg = torch.cat([yg, yp.reshape(1, -1)], 1)
    n_all = xg.shape[1]
    kernels = _kernels(settings, device)
    blocks = [GridBlock(0, settings.npix * k, settings.pixel_scale / k)]
    if k > 1:
        blocks.append(GridBlock(blocks[0].m ** 2, settings.npix, settings.pixel_scale))
    geometry = _Geometry(tuple(blocks), len(blocks) - 1, (xg, yg))
    if device.type == "cpu" and _PER_IMAGE_ON_CPU:
        groups = [np.array([i]) for i in range(n)]
    else:
        bs = max(1, settings.max_elements // (chunk_width(settings, n_all, kernels.compiled) * n_all))
        groups = [np.arange(s, min(n, s + bs)) for s in range(0, n, bs)]
    with torch.no_grad():
        out = [_render_group(g, macro, psf_t, settings, sources, subhalos, los, smooth,
                             (xg, yg, n_pix), device, kernels, geometry) for g in groups]
    return torch.cat(out, 0)


def render_smooth(macro: dict[str, np.ndarray], psf: Tensor, settings: RenderSettings, *,
                  sources: PixelatedSources | None = None) -> Tensor:
    """Noise-free smooth model, ``(B, npix, npix)`` e⁻/s per pixel: main-lens EPL + shear +
    multipoles + source, PSF-convolved; no lens light, no subhalos, no LoS (used to
    place subhalos on the arc)."""
    return _render(macro, psf, settings, sources, None, None, smooth=True)


def render(macro: dict[str, np.ndarray], psf: Tensor, settings: RenderSettings, *,
           sources: PixelatedSources | None = None, subhalos=None, los=None) -> Tensor:
    """Noise-free full image, ``(B, npix, npix)`` e⁻/s per pixel.

    ``macro``: :func:`subslope.scenes.sample_macro` output (absent keys = component off);
    ``psf``: odd 2-D kernel (sum 1) at the pixel scale; ``sources``: pixelated sources,
    or None with Sérsic source keys in ``macro``; ``subhalos``:
    :class:`subslope.subhalos.SubhaloPopulation` ('epl' | 'nfw' | 'tnfw'); ``los``:
    :class:`subslope.los.LosPopulation` (reduced deflections for each system's z_source).
    """
    return _render(macro, psf, settings, sources, subhalos, los, smooth=False)
