"""Batched, noise-free renderer of lens images (``docs/physics.md``, ``docs/simulation.md``).

Pipeline for a batch of ``B`` systems, one function per step (``docs/simulation.md``):

1. coordinates: the ``(npix·k)²`` sub-pixel grid (``k = supersample``) plus, when
   ``k > 1``, the ``npix²`` pixel centres (needed for the negative sheets);
2. lens equation: main-lens EPL (amplitude θ_E^(γ−1)) + external shear (about the
   origin) + m = 3, 4 multipoles (about the lens centre) + the subhalo population and
   its negative sheet, all in the lens plane; with line-of-sight halos, one extra plane
   per slice redshift (own negative sheet) and
   :func:`subslope.physics.raytrace.multi_plane_ray_shoot`;
3. source surface brightness at β (COSMOS stamps via :mod:`subslope.physics.light.pixelated`, or
   an elliptical Sérsic rotated by ``src_rotation``, or a multi-Sérsic source: a sum of
   Sérsic components whose shapes and centre offsets rotate with ``src_rotation``),
   plus the unlensed Sérsic lens light;
4. binning of the k×k sub-pixels, × pixel area (e⁻/s per pixel), PSF convolution
   (:func:`subslope.physics.instrument.convolve`, the batch at once).

Negative sheets: ``κ_sheet = −(1/P) Σ_pixels Σ_members κ_i`` with the member
convergences taken at the pixel-centre rays *on that plane* (for the main-lens plane of
a single-plane scene: the pixel centres themselves); the sheet deflection is
``κ_sheet·(x − c_x, y − c_y)`` about the plane's origin (``c = 0``, the reference) or
the population's κ-weighted centre over those rays (``sheet_centre='mass_centroid'``).
The summed convergence comes out of the same fused pass as the deflections (one extra
multiply), so the sheet costs no second pass over the population.

Components whose macro keys are absent (or populations that are empty) are not
evaluated at all; every evaluated step increments
:data:`subslope.render.counters.STEP_COUNTS`.

Population passes (subhalos, LoS halos) run on member tables and fused pair kernels
(:mod:`subslope.physics.pairs.sums`, ``torch.compile``'d on CPU); large populations use the
near/far split of :mod:`subslope.render.nearfar` (``RenderSettings.population``);
:mod:`subslope.render.populations` holds the population passes,
:mod:`subslope.render.kernels` the compiled kernels, :mod:`subslope.render.settings`
the knobs.

Batches (``RenderSettings.batching = 'auto'``): the images of a render call are
rendered ``batch_images`` at a time, every step on the whole batch. The line-of-sight
slices of its images share planes by rank (:func:`subslope.render.planes.slice_ranks`;
inactive planes are exact no-ops); the subhalo population is one padded pass (one pass
per image on a CPU with the near/far split, where padding would only add pairs). The
same batch gives the same bits; an image alone and in a batch agree to float rounding
(element-wise float32 kernels take a vectorised or a scalar path depending on where an
element falls in the tensor, and member sums are compiled reductions whose order may
depend on the padded width). ``batching = 'per_image'`` renders one image at a time.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from subslope.devices import pick_device
from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import (
    KernelSpectrum,
    convolution_method,
    convolve,
    kernel_spectrum,
)
from subslope.physics.light.pixelated import pixelated_light
from subslope.physics.light.sersic import multi_sersic_from_magnitude, sersic_ellipse_from_magnitude
from subslope.physics.pairs.epl import epl_table
from subslope.physics.profiles.epl import theta_e_to_amp
from subslope.physics.profiles.multipole import multipole_deflections
from subslope.physics.profiles.shear import shear_deflection
from subslope.physics.raytrace import Plane, multi_plane_ray_shoot
from subslope.render.counters import count_step
from subslope.render.inputs import (
    GROUPS,
    check_macro,
    has_group,
    multi_sersic_slots,
    sheet_centre_pair,
)
from subslope.render.kernels import Kernels, kernels_for
from subslope.render.planes import flat_members, los_planes
from subslope.render.populations import (
    PROFILE_KEYS,
    Geometry,
    Population,
    main_lens_deflection,
    pack_population,
    population_pass,
    select_systems,
    use_split,
)
from subslope.render.settings import PixelatedSources, RenderSettings, chunk_width
from subslope.render.tiles import GridBlock

__all__ = ["RenderSettings", "PixelatedSources", "render_smooth", "render"]


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
@dataclass(frozen=True)
class _Batch:
    """One sub-batch of a render call: images ``idx`` of ``macro`` and what every step
    of it shares (settings, device, kernels, the point layout)."""

    idx: np.ndarray
    macro: dict
    settings: RenderSettings
    device: torch.device
    kernels: Kernels
    geometry: Geometry
    grid: tuple[Tensor, Tensor, int]
    sheet: tuple[str, str] = ("origin", "origin")
    #: whether the halos' own deflections are rendered (False: their sheets only)
    members: bool = True
    #: macro parameters of every image of the render call, converted once
    #: (:meth:`par`), shared by its sub-batches
    columns: dict = dataclasses.field(default_factory=dict)

    @property
    def size(self) -> int:
        return self.idx.size

    def par(self, key: str) -> Tensor:
        """Macro parameter ``key`` of the sub-batch, ``(b, 1)`` in the render dtype."""
        col = self.columns.get(key)
        if col is None:
            col = self.columns[key] = torch.as_tensor(
                np.asarray(self.macro[key], dtype=np.float64),
                dtype=self.settings.dtype,
                device=self.device,
            )
        lo, hi = int(self.idx[0]), int(self.idx[-1]) + 1
        if hi - lo == self.idx.size:  # sub-batches are runs of consecutive images
            return col[lo:hi, None]
        return col[torch.as_tensor(self.idx, device=self.device)][:, None]

    def values(self, key: str) -> np.ndarray:
        """Macro parameter ``key`` of the sub-batch, ``(b,)`` float64."""
        return np.asarray(self.macro[key], dtype=np.float64)[self.idx]


def _subhalo_populations(batch: _Batch, subhalos) -> list[tuple[slice, Population]]:
    """The lens-plane subhalos of the sub-batch: ``(images, population)`` pairs, empty
    when there are none. One padded population for the sub-batch, except with batching
    'auto' on a CPU where the near/far split applies: there one population per image,
    since padding every image to the largest member count would add pairs (N_sub is
    drawn per image) and a CPU gains nothing from evaluating the pairs in one call."""
    if subhalos is None:
        return []
    counts, sel = select_systems(subhalos.counts, batch.idx)
    if counts.sum() == 0:
        return []
    s = batch.settings
    flat = flat_members(subhalos, sel)

    def pack(c, members):
        return pack_population(
            subhalos.profile,
            members,
            c,
            s.n_terms,
            s.dtype,
            batch.device,
            batch.sheet[0],
            batch.members,
        )

    padded = batch.device.type != "cpu" or s.batching == "sub_batch"
    if batch.size == 1 or padded or not use_split(counts, s, batch.geometry):
        return [(slice(0, batch.size), pack(counts, flat))]
    off = np.concatenate([[0], np.cumsum(counts)])
    return [
        (
            slice(i, i + 1),
            pack(
                counts[i : i + 1],
                {k: None if v is None else v[off[i] : off[i + 1]] for k, v in flat.items()},
            ),
        )
        for i in range(batch.size)
        if counts[i] > 0
    ]


def _lens_plane(batch: _Batch, sub_pops: list[tuple[slice, Population]]):
    """The deflection of the main-lens plane, ``(tx, ty, displaced) -> (ax, ay)``: EPL +
    shear + multipoles + the subhalo population and its sheet."""
    settings, kernels, par = batch.settings, batch.kernels, batch.par
    n_pix = batch.grid[2]
    lens_amp = theta_e_to_amp(par("theta_e"), par("gamma_ml"))
    lens = {kk: par(kk) for kk in ("gamma_ml", "lens_e1", "lens_e2", "lens_x", "lens_y")}
    lens_table = epl_table(
        {
            "amp": lens_amp,
            "gamma": lens["gamma_ml"],
            "e1": lens["lens_e1"],
            "e2": lens["lens_e2"],
            "x": lens["lens_x"],
            "y": lens["lens_y"],
        },
        settings.n_terms_main,
    ).contiguous()
    shear = {kk: par(kk) for kk in GROUPS["shear"]} if has_group(batch.macro, "shear") else None
    mpole = (
        {kk: par(kk) for kk in GROUPS["multipoles"]}
        if has_group(batch.macro, "multipoles")
        else None
    )

    def lens_plane(tx: Tensor, ty: Tensor, displaced: bool = True) -> tuple[Tensor, Tensor]:
        count_step("main_lens")
        ax, ay = main_lens_deflection(tx, ty, lens_table, kernels)
        if shear is not None:
            count_step("shear")
            sx, sy = shear_deflection(tx, ty, shear["shear_g1"], shear["shear_g2"])
            ax, ay = ax + sx, ay + sy
        if mpole is not None:
            count_step("multipoles")
            for mx, my in multipole_deflections(
                tx,
                ty,
                (3, 4),
                (mpole["a3"], mpole["a4"]),
                (mpole["phi3"], mpole["phi4"]),
                lens["lens_x"],
                lens["lens_y"],
            ):
                ax, ay = ax + mx, ay + my
        if sub_pops:
            count_step("subhalos")
            geo = (
                batch.geometry
                if displaced
                else dataclasses.replace(batch.geometry, displaced=False)
            )
            if len(sub_pops) == 1 and sub_pops[0][0] == slice(0, batch.size):
                px, py, _ = population_pass(sub_pops[0][1], tx, ty, settings, kernels, n_pix, geo)
            else:  # one pass per image; images without subhalos add exact zeros
                px, py = torch.zeros_like(ax), torch.zeros_like(ay)
                for sl, pop in sub_pops:
                    px[sl], py[sl], _ = population_pass(
                        pop, tx[sl], ty[sl], settings, kernels, n_pix, geo
                    )
            ax, ay = ax + px, ay + py
        return ax, ay

    return lens_plane


def _trace(batch: _Batch, planes: list[Plane], lens_plane, zs: np.ndarray) -> tuple[Tensor, Tensor]:
    """Source-plane positions ``(b, P)`` of every ray: multi-plane with LoS planes,
    else the single lens plane."""
    xg, yg, _ = batch.grid
    b = batch.size
    if planes:
        count_step("multi_plane")
        return multi_plane_ray_shoot(xg.expand(b, -1), yg.expand(b, -1), planes, zs)
    count_step("single_plane")
    ax, ay = lens_plane(xg.expand(b, -1), yg.expand(b, -1), displaced=False)
    return xg - ax, yg - ay


def _multi_sersic_source(batch: _Batch, bx: Tensor, by: Tensor, kmax: int) -> Tensor:
    """Surface brightness of a multi-Sérsic source: components rotated with the source."""
    par, idx = batch.par, batch.idx
    count_step("source_multi_sersic")
    rot = par("src_rotation")
    c2, s2 = torch.cos(2 * rot), torch.sin(2 * rot)
    c1, s1 = torch.cos(rot), torch.sin(rot)
    cx, cy = par("src_x"), par("src_y")
    # Components switched off (zero flux for every image of the sub-batch) are skipped.
    active = [j for j in range(kmax) if np.any(np.asarray(batch.macro[f"src_frac_{j}"])[idx] > 0)]
    comp: dict[str, list] = {kk: [] for kk in ("f", "r", "n", "e1", "e2", "x", "y")}
    for j in active:
        count_step("source_component")
        e1, e2 = par(f"src_e1_{j}"), par(f"src_e2_{j}")
        dx, dy = par(f"src_dx_{j}"), par(f"src_dy_{j}")
        comp["f"].append(par(f"src_frac_{j}"))
        comp["r"].append(par(f"src_r_{j}"))
        comp["n"].append(par(f"src_n_{j}"))
        comp["e1"].append(c2 * e1 - s2 * e2)
        comp["e2"].append(s2 * e1 + c2 * e2)
        comp["x"].append(cx + c1 * dx - s1 * dy)
        comp["y"].append(cy + s1 * dx + c1 * dy)
    return multi_sersic_from_magnitude(
        bx,
        by,
        par("src_mag_total"),
        comp["f"],
        comp["r"],
        comp["n"],
        comp["e1"],
        comp["e2"],
        comp["x"],
        comp["y"],
        zero_point=batch.settings.zero_point,
    )


def _source_light(
    batch: _Batch, bx: Tensor, by: Tensor, sources: PixelatedSources | None
) -> Tensor:
    """Source surface brightness at the source-plane positions (multi-Sérsic, Sérsic or
    pixelated), e⁻/s per arcsec²."""
    par, settings, device = batch.par, batch.settings, batch.device
    kmax = multi_sersic_slots(batch.macro)
    if kmax:
        return _multi_sersic_source(batch, bx, by, kmax)
    if sources is None:
        count_step("source_sersic")
        rot = par("src_rotation")
        e1, e2 = par("src_e1"), par("src_e2")
        c2, s2 = torch.cos(2 * rot), torch.sin(2 * rot)
        return sersic_ellipse_from_magnitude(
            bx,
            by,
            par("src_mag"),
            par("src_r"),
            par("src_n"),
            c2 * e1 - s2 * e2,
            s2 * e1 + c2 * e2,
            par("src_x"),
            par("src_y"),
            zero_point=settings.zero_point,
        )
    count_step("source_pixelated")
    dtype, idx = settings.dtype, batch.idx
    st = torch.as_tensor(sources.stamps)
    st = st[torch.as_tensor(idx, device=st.device)].to(dtype=dtype, device=device)
    offs = torch.as_tensor(sources.offsets)[torch.as_tensor(idx)].to(dtype=dtype, device=device)
    ps = torch.as_tensor(
        np.asarray(sources.pixel_scale, dtype=np.float64)[idx], dtype=dtype, device=device
    )[:, None]
    return pixelated_light(
        bx,
        by,
        st,
        ps,
        par("src_rotation"),
        par("src_x"),
        par("src_y"),
        order=settings.source_interpolation,
        stamp_offset_x=offs[:, 0:1],
        stamp_offset_y=offs[:, 1:2],
    )


def _observe(
    batch: _Batch, sb: Tensor, psf: Tensor, spectrum: KernelSpectrum | None, smooth: bool
) -> Tensor:
    """Add the lens light, bin the sub-pixels, × pixel area, convolve with the PSF and
    add the sky level: ``(b, npix, npix)`` e⁻/s per pixel."""
    settings, par = batch.settings, batch.par
    xg, yg, _ = batch.grid
    k = settings.supersample
    n_ss = (settings.npix * k) ** 2
    if not smooth and has_group(batch.macro, "lens_light"):
        count_step("lens_light")
        sb = sb + sersic_ellipse_from_magnitude(
            xg[:, :n_ss],
            yg[:, :n_ss],
            par("light_mag"),
            par("light_r"),
            par("light_n"),
            par("light_e1"),
            par("light_e2"),
            par("lens_x"),
            par("lens_y"),
            zero_point=settings.zero_point,
        )
    m = settings.npix * k
    img = sb.reshape(batch.size, m, m)
    if k > 1:
        count_step("supersample_bin")
        img = _bin(img, k)
    img = img * (settings.pixel_scale**2)
    count_step("psf")
    img = convolve(img, psf, method=settings.convolution, spectrum=spectrum)
    if not smooth and has_group(batch.macro, "sky"):
        count_step("sky")
        img = img + par("sky_level")[:, :, None]
    return img


def _render_group(
    batch: _Batch,
    psf: tuple[Tensor, KernelSpectrum | None],
    sources: PixelatedSources | None,
    subhalos,
    los,
    smooth: bool,
) -> Tensor:
    """The images of one sub-batch: trace the rays through the planes, then observe."""
    zl, zs = batch.values("z_lens"), batch.values("z_source")
    lens_plane = _lens_plane(batch, [] if smooth else _subhalo_populations(batch, subhalos))
    planes = [] if smooth else los_planes(batch, los, lens_plane, zl, zs)
    bx, by = _trace(batch, planes, lens_plane, zs)
    n_ss = (batch.settings.npix * batch.settings.supersample) ** 2
    sb = _source_light(batch, bx[:, :n_ss], by[:, :n_ss], sources)
    return _observe(batch, sb, *psf, smooth)


def _check_populations(n: int, subhalos, los) -> None:
    if subhalos is not None and len(subhalos.counts) != n:
        raise ValueError(f"subhalos.counts has {len(subhalos.counts)} systems, macro has {n}")
    if los is not None and len(los.counts) != n:
        raise ValueError(f"los.counts has {len(los.counts)} systems, macro has {n}")
    if subhalos is not None and subhalos.profile not in PROFILE_KEYS:
        raise ValueError(
            f"subhalos.profile must be one of {tuple(PROFILE_KEYS)}, got {subhalos.profile!r}"
        )


def _points(settings: RenderSettings, device: torch.device) -> tuple[Tensor, Tensor, Geometry]:
    """The rays of a render call ``(1, P)``: the sub-pixel grid, then (supersampled) the
    pixel centres that the negative sheets use, and their block layout."""
    dtype, k = settings.dtype, settings.supersample
    xs, ys = pixel_grid(settings.npix, settings.pixel_scale, k, dtype=dtype, device=device)
    xg, yg = xs.reshape(1, -1), ys.reshape(1, -1)
    if k > 1:  # append the pixel centres (rays used for the negative sheets)
        xp, yp = pixel_grid(settings.npix, settings.pixel_scale, 1, dtype=dtype, device=device)
        xg = torch.cat([xg, xp.reshape(1, -1)], 1)
        yg = torch.cat([yg, yp.reshape(1, -1)], 1)
    blocks = [GridBlock(0, settings.npix * k, settings.pixel_scale / k)]
    if k > 1:
        blocks.append(GridBlock(blocks[0].m ** 2, settings.npix, settings.pixel_scale))
    return xg, yg, Geometry(tuple(blocks), len(blocks) - 1, (xg, yg))


def _sub_batches(
    n: int, n_all: int, settings: RenderSettings, device: torch.device, kernels: Kernels
) -> list[np.ndarray]:
    """Image indices of each sub-batch (:attr:`RenderSettings.batching`)."""
    if settings.batching == "per_image":
        return [np.array([i]) for i in range(n)]
    if settings.batching == "auto":
        bs = settings.batch_images
    else:
        bs = max(
            1, settings.max_elements // (chunk_width(settings, n_all, kernels.compiled) * n_all)
        )
    return [np.arange(s, min(n, s + bs)) for s in range(0, n, bs)]


def _render(
    macro,
    psf,
    settings: RenderSettings,
    sources,
    subhalos,
    los,
    smooth: bool,
    sheet=("origin", "origin"),
    members: bool = True,
) -> Tensor:
    if not isinstance(settings, RenderSettings):
        raise ValueError(f"settings must be a RenderSettings, got {type(settings).__name__}")
    n = check_macro(macro, sources)
    _check_populations(n, subhalos, los)
    device = pick_device(settings.device, key="simulation.render.device")
    psf_t = torch.as_tensor(psf).to(dtype=settings.dtype, device=device)
    fft = convolution_method(settings.convolution, psf_t.shape, device) == "fft"
    spectrum = kernel_spectrum(psf_t, (settings.npix, settings.npix)) if fft else None
    xg, yg, geometry = _points(settings, device)
    kernels = kernels_for(settings, device)
    grid = (xg, yg, settings.npix**2)
    columns: dict[str, Tensor] = {}
    with torch.no_grad():
        out = [
            _render_group(
                _Batch(
                    g, macro, settings, device, kernels, geometry, grid, sheet, members, columns
                ),
                (psf_t, spectrum),
                sources,
                subhalos,
                los,
                smooth,
            )
            for g in _sub_batches(n, xg.shape[1], settings, device, kernels)
        ]
    return torch.cat(out, 0)


def render_smooth(
    macro: dict[str, np.ndarray],
    psf: Tensor,
    settings: RenderSettings,
    *,
    sources: PixelatedSources | None = None,
) -> Tensor:
    """Noise-free smooth model, ``(B, npix, npix)`` e⁻/s per pixel: main-lens EPL + shear +
    multipoles + source, PSF-convolved; no lens light, no subhalos, no LoS (used to
    place subhalos on the arc)."""
    return _render(macro, psf, settings, sources, None, None, smooth=True)


def render(
    macro: dict[str, np.ndarray],
    psf: Tensor,
    settings: RenderSettings,
    *,
    sources: PixelatedSources | None = None,
    subhalos=None,
    los=None,
    sheet_centre="origin",
    members: bool = True,
) -> Tensor:
    """Noise-free full image, ``(B, npix, npix)`` e⁻/s per pixel.

    ``macro``: :func:`subslope.simulation.macro.sample_macro` output (absent keys = component off);
    ``psf``: odd 2-D kernel (sum 1) at the pixel scale; ``sources``: pixelated sources,
    or None with Sérsic source keys in ``macro``; ``subhalos``:
    :class:`subslope.simulation.subhalos.SubhaloPopulation` ('epl' | 'nfw' | 'tnfw'); ``los``:
    :class:`subslope.simulation.los_halos.LosPopulation` (reduced deflections for each
    system's z_source);
    ``sheet_centre``: where the negative sheets are centred, ``origin`` or
    ``mass_centroid`` (:data:`subslope.render.populations.SHEET_CENTRES`), one name for
    every plane or ``{"subhalos": ..., "los": ...}``; ``members=False``: the negative
    sheets of ``subhalos`` and ``los`` without the halos themselves (null tests).
    """
    sheet = sheet_centre_pair(sheet_centre)
    return _render(
        macro, psf, settings, sources, subhalos, los, smooth=False, sheet=sheet, members=members
    )
