"""Diagnostics of the stiff physical cases of SCIENCE.md §4 (EPL subhalos at γ ≫ 2 and γ → 1).

:func:`stiff_cases` renders one system of the ``train`` scene (Sérsic, multi-Sérsic or
COSMOS source; lens light, line-of-sight halos and noise off; PSF on) with N_sub EPL
subhalos placed on the arc of its smooth model, for several labels γ with the *same*
masses, positions and ellipticities (the per-subhalo slopes γ_i follow from γ with the
same random numbers), with and without the negative mass sheet, and returns the images
and a table of numbers (:class:`StiffCase`):

- ``arc_ratio``: flux inside the smooth model's arc mask (smooth > ``threshold_fraction``
  × its maximum) divided by the smooth model's flux there;
- ``centre_flux``: flux of the 5×5 pixels around the lens centre (e⁻/s);
- ``total_ratio``: total flux / smooth model's total flux;
- ``kappa_mean``, ``kappa_min``, ``kappa_max``: mean over the image pixels and min / max
  over the field of the summed subhalo convergence (lens plane, pixel centres, before
  the sheet); ``kappa_sheet`` = −``kappa_mean`` when the sheet is on, else 0; and
  ``kappa_total_mean``, the pixel mean of subhalos + sheet.

The run without the sheet is a diagnostic only (the renderer always includes the sheet):
it wraps :func:`subslope.render._population_pass` so that the sheet's deflection is
subtracted again (:func:`sheet_off`).

:func:`lenstronomy_image` renders the same inputs with lenstronomy (an optional,
test-only reference: EPL main lens, SHEAR, two MULTIPOLEs, EPL subhalos with
θ_E = A^(1/(γ−1)) and a CONVERGENCE sheet of −mean κ over the pixel centres,
SERSIC_ELLIPSE source, PIXEL PSF).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from subslope import render as R
from subslope import scenes as _scenes
from subslope import subhalos as _subhalos
from subslope.grid import pixel_grid
from subslope.profiles.epl import epl_convergence

__all__ = ["StiffCase", "stiff_system", "stiff_cases", "summed_subhalo_kappa", "sheet_off",
           "lenstronomy_image", "format_table"]


@dataclass
class StiffCase:
    """Numbers of one rendered case (see the module docstring)."""

    label: str
    gamma: float | None
    n_sub: int
    sheet: bool
    arc_ratio: float
    centre_flux: float
    total_ratio: float
    kappa_mean: float
    kappa_min: float
    kappa_max: float
    kappa_sheet: float
    kappa_total_mean: float


@contextlib.contextmanager
def sheet_off():
    """Within the block, rendered subhalo populations carry no negative sheet (diagnostic)."""
    orig = R._population_pass

    def no_sheet(pop, x, y, *args, **kwargs):
        ax, ay, k = orig(pop, x, y, *args, **kwargs)
        return ax - k * x, ay - k * y, torch.zeros_like(k)

    R._population_pass = no_sheet
    try:
        yield
    finally:
        R._population_pass = orig


def summed_subhalo_kappa(subs, npix: int = 100, pixel_scale: float = 0.04, chunk: int = 128) -> np.ndarray:
    """Summed convergence of an EPL population of ONE system at the pixel centres, (npix, npix), float64."""
    x, y = pixel_grid(npix, pixel_scale, dtype=torch.float64)
    x, y = x.reshape(1, -1), y.reshape(1, -1)
    total = torch.zeros(x.shape[1], dtype=torch.float64)
    n = int(np.sum(subs.counts))
    for s in range(0, n, chunk):
        p = {k: torch.as_tensor(np.asarray(getattr(subs, k))[s:s + chunk], dtype=torch.float64)[:, None]
             for k in ("amp", "gamma", "e1", "e2", "x", "y")}
        total += epl_convergence(x, y, p["amp"], p["gamma"], p["e1"], p["e2"], p["x"], p["y"]).sum(0)
    return total.reshape(npix, npix).numpy()


def stiff_system(seed: int = 6, source: str = "sersic") -> tuple[_scenes.Scene, dict[str, np.ndarray]]:
    """One ``train``-scene system (lens light and LoS off) with a parametric source."""
    scene = _scenes.Scene.from_config(
        "train", {"source": {"kind": source}, "components": {"los": False, "lens_light": False}})
    return scene, _scenes.sample_macro(scene, 1, np.random.default_rng(seed))


def _cosmos_sources(macro, folder, seed):
    from subslope.light.pixelated import pad_stamps
    from subslope.sources.cosmos import CosmosCatalog, place_at_redshift

    cat = CosmosCatalog.load(folder)
    row = cat.table.iloc[int(np.random.default_rng(seed).integers(len(cat.table)))]
    sb, ps = place_at_redshift(cat.stamp(int(row["ident"])), float(row["pixel_scale"]), float(row["zphot"]),
                               float(macro["z_source"][0]))
    st, off = pad_stamps([sb], dtype=torch.float64)
    return R.PixelatedSources(stamps=st, pixel_scale=np.asarray([ps]), offsets=off)


def stiff_cases(
    psf,
    *,
    seed: int = 6,
    n_sub: int = 1500,
    gammas=(2.5, 1.2),
    sheets=(True, False),
    source: str = "sersic",
    cosmos_folder=None,
    settings: R.RenderSettings | None = None,
    macro: dict[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Render the stiff cases of one system; returns ``images`` (label → (H, W) numpy),
    ``cases`` (list of :class:`StiffCase`, first the smooth reference N_sub = 0),
    ``arc_mask``, ``macro``, ``subhalos`` (γ → population) and ``centre`` (row, col slices).

    ``source``: 'sersic' | 'multi_sersic' | 'cosmos' (a galaxy of ``cosmos_folder``).
    ``macro`` overrides the drawn system (one system, keys as :func:`stiff_system`).
    """
    settings = settings or R.RenderSettings(device="cpu", dtype=torch.float64, compile="off")
    kind = "sersic" if source == "cosmos" else source
    scene, drawn = stiff_system(seed, kind)
    macro = dict(macro) if macro is not None else drawn
    sources = None
    if source == "cosmos":
        for k in ("src_mag", "src_r", "src_n", "src_e1", "src_e2"):
            macro.pop(k, None)
        sources = _cosmos_sources(macro, cosmos_folder, seed)
    macro["n_sub"] = np.array([n_sub], dtype=np.int64)
    psf = torch.as_tensor(psf, dtype=settings.dtype)
    smooth = R.render_smooth(macro, psf, settings, sources=sources)[0].cpu().numpy().astype(np.float64)
    frac = scene.subhalos.threshold_fraction
    arc = smooth > frac * smooth.max()
    n, d = settings.npix, settings.pixel_scale
    jc = int(round(macro["lens_y"][0] / d + (n - 1) / 2))
    ic = int(round(macro["lens_x"][0] / d + (n - 1) / 2))
    centre = (slice(jc - 2, jc + 3), slice(ic - 2, ic + 3))

    def numbers(label, img, gamma, sheet, kap):
        km = float(kap.mean()) if kap is not None else 0.0
        ks = -km if sheet else 0.0
        return StiffCase(label, gamma, 0 if kap is None else n_sub, sheet,
                         float(img[arc].sum() / smooth[arc].sum()), float(img[centre].sum()),
                         float(img.sum() / smooth.sum()), km,
                         float(kap.min()) if kap is not None else 0.0,
                         float(kap.max()) if kap is not None else 0.0, ks, km + ks)

    images = {"smooth (N_sub = 0)": smooth}
    cases = [numbers("smooth (N_sub = 0)", smooth, None, False, None)]
    pops = {}
    for gam in gammas:
        m = dict(macro, gamma_sub=np.array([float(gam)]))
        subs = _subhalos.sample_subhalos(scene, m, np.random.default_rng(seed + 1), smooth_images=smooth[None])
        pops[gam] = subs
        kap = summed_subhalo_kappa(subs, n, d)
        for sheet in sheets:
            ctx = contextlib.nullcontext() if sheet else sheet_off()
            with ctx:
                img = R.render(m, psf, settings, sources=sources, subhalos=subs)[0].cpu().numpy().astype(np.float64)
            label = f"γ = {gam:g}, N_sub = {n_sub}, sheet {'on' if sheet else 'off'}"
            images[label] = img
            cases.append(numbers(label, img, float(gam), sheet, kap))
    return {"images": images, "cases": cases, "arc_mask": arc, "macro": macro, "subhalos": pops,
            "centre": centre, "sources": sources, "settings": settings}


def format_table(cases) -> str:
    """Markdown table of :class:`StiffCase` rows."""
    head = ("| case | arc flux / smooth | central 5×5 (e⁻/s) | total / smooth | mean Σκ_sub | "
            "min Σκ_sub | max Σκ_sub | κ_sheet | mean(Σκ_sub + sheet) |\n|---|---|---|---|---|---|---|---|---|")
    rows = [f"| {c.label} | {c.arc_ratio:.3f} | {c.centre_flux:.4f} | {c.total_ratio:.3f} | {c.kappa_mean:.3f} | "
            f"{c.kappa_min:.3f} | {c.kappa_max:.3f} | {c.kappa_sheet:.3f} | {c.kappa_total_mean:.1e} |"
            for c in cases]
    return "\n".join([head, *rows])


def lenstronomy_image(macro: dict[str, np.ndarray], subs, psf, *, npix: int = 100, pixel_scale: float = 0.04,
                      sheet: bool = True, supersampling: int = 1) -> np.ndarray:
    """lenstronomy's noise-free image of system 0 of ``macro`` (Sérsic source) with the EPL
    population ``subs`` and, if ``sheet``, a CONVERGENCE sheet of −(mean summed subhalo κ
    over the pixel centres, computed by lenstronomy). Reference only (imports lenstronomy)."""
    from lenstronomy.Data.imaging_data import ImageData
    from lenstronomy.Data.psf import PSF as LPSF
    from lenstronomy.ImSim.image_model import ImageModel
    from lenstronomy.LensModel.lens_model import LensModel
    from lenstronomy.LightModel.light_model import LightModel

    from subslope.light.sersic import magnitude_to_flux, sersic_amp_from_flux

    g = {k: float(np.asarray(v)[0]) for k, v in macro.items()}
    kw = [dict(theta_E=g["theta_e"], gamma=g["gamma_ml"], e1=g["lens_e1"], e2=g["lens_e2"],
               center_x=g["lens_x"], center_y=g["lens_y"])]
    models = ["EPL"]
    if "shear_g1" in g:
        kw.append(dict(gamma1=g["shear_g1"], gamma2=g["shear_g2"], ra_0=0.0, dec_0=0.0))
        models.append("SHEAR")
    if "a3" in g:
        for m, a, p in ((3, "a3", "phi3"), (4, "a4", "phi4")):
            kw.append(dict(m=m, a_m=g[a], phi_m=g[p], center_x=g["lens_x"], center_y=g["lens_y"]))
            models.append("MULTIPOLE")
    sub_kw = [dict(theta_E=float(np.exp(np.log(a) / (gm - 1))), gamma=float(gm), e1=float(e1), e2=float(e2),
                   center_x=float(x), center_y=float(y))
              for a, gm, e1, e2, x, y in zip(subs.amp, subs.gamma, subs.e1, subs.e2, subs.x, subs.y)]
    if sub_kw:
        kw += sub_kw
        models += ["EPL"] * len(sub_kw)
        if sheet:
            xx, yy = pixel_grid(npix, pixel_scale, dtype=torch.float64)
            kap = LensModel(["EPL"] * len(sub_kw)).kappa(xx.numpy().ravel(), yy.numpy().ravel(), sub_kw)
            kw.append(dict(kappa=-float(np.mean(kap)), ra_0=0.0, dec_0=0.0))
            models.append("CONVERGENCE")
    rot = g["src_rotation"]
    c2, s2 = np.cos(2 * rot), np.sin(2 * rot)
    amp = float(sersic_amp_from_flux(magnitude_to_flux(g["src_mag"]), g["src_r"], g["src_n"]))
    kw_src = [dict(amp=amp, R_sersic=g["src_r"], n_sersic=g["src_n"], e1=c2 * g["src_e1"] - s2 * g["src_e2"],
                   e2=s2 * g["src_e1"] + c2 * g["src_e2"], center_x=g["src_x"], center_y=g["src_y"])]
    n, d = npix, pixel_scale
    data = ImageData(image_data=np.zeros((n, n)), ra_at_xy_0=-(n - 1) / 2 * d, dec_at_xy_0=-(n - 1) / 2 * d,
                     transform_pix2angle=np.array([[d, 0], [0, d]]))
    lpsf = LPSF(psf_type="PIXEL", kernel_point_source=np.asarray(psf, dtype=np.float64))
    im = ImageModel(data, lpsf, lens_model_class=LensModel(models), source_model_class=LightModel(["SERSIC_ELLIPSE"]),
                    kwargs_numerics={"supersampling_factor": supersampling})
    return np.asarray(im.image(kwargs_lens=kw, kwargs_source=kw_src))
