"""Diagnostics of the stiff physical cases of docs/simulation.md (EPL subhalos at γ ≫ 2 and γ → 1).

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
it wraps :func:`subslope.render.pipeline._population_pass` so that the sheet's deflection is
subtracted again (:func:`sheet_off`).

:func:`subslope.validation.lenstronomy.lenstronomy_model` renders the same inputs with lenstronomy
(an optional,
test-only reference: EPL main lens, SHEAR, two MULTIPOLEs, EPL subhalos with
θ_E = A^(1/(γ−1)) and a CONVERGENCE sheet of −mean κ over the pixel centres,
SERSIC_ELLIPSE source, PIXEL PSF).
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import NPIX, PIXEL_SCALE
from subslope.physics.profiles.epl import epl_convergence
from subslope.render import pipeline as R
from subslope.simulation import macro as _macro
from subslope.simulation import scenes as _scenes
from subslope.simulation import subhalos as _subhalos

__all__ = [
    "StiffCase",
    "stiff_system",
    "stiff_cases",
    "summed_subhalo_kappa",
    "sheet_off",
    "format_table",
]


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
    sheet_centre: str = "origin"


@contextlib.contextmanager
def sheet_off():
    """Within the block, rendered subhalo populations carry no negative sheet (diagnostic)."""
    orig = R.population_pass

    def no_sheet(pop, x, y, *args, **kwargs):
        ax, ay, k = orig(dataclasses.replace(pop, sheet_centre="origin"), x, y, *args, **kwargs)
        return ax - k * x, ay - k * y, torch.zeros_like(k)

    R.population_pass = no_sheet
    try:
        yield
    finally:
        R.population_pass = orig


def summed_subhalo_kappa(
    subs, npix: int = NPIX, pixel_scale: float = PIXEL_SCALE, chunk: int = 128
) -> np.ndarray:
    """Summed convergence of an EPL population of ONE system at the pixel centres, (npix, npix),
    float64."""
    x, y = pixel_grid(npix, pixel_scale, dtype=torch.float64)
    x, y = x.reshape(1, -1), y.reshape(1, -1)
    total = torch.zeros(x.shape[1], dtype=torch.float64)
    n = int(np.sum(subs.counts))
    for s in range(0, n, chunk):
        p = {
            k: torch.as_tensor(np.asarray(getattr(subs, k))[s : s + chunk], dtype=torch.float64)[
                :, None
            ]
            for k in ("amp", "gamma", "e1", "e2", "x", "y")
        }
        total += epl_convergence(x, y, p["amp"], p["gamma"], p["e1"], p["e2"], p["x"], p["y"]).sum(
            0
        )
    return total.reshape(npix, npix).numpy()


def stiff_system(
    seed: int = 6, source: str = "sersic"
) -> tuple[_scenes.Scene, dict[str, np.ndarray]]:
    """One ``train``-scene system (lens light and LoS off) with a parametric source."""
    scene = _scenes.Scene.from_config(
        "train", {"source": {"kind": source}, "components": {"los": False, "lens_light": False}}
    )
    return scene, _macro.sample_macro(scene, 1, np.random.default_rng(seed))


def _cosmos_sources(macro, folder, seed):
    from subslope.io.cosmos import CosmosCatalog, place_at_redshift
    from subslope.physics.light.pixelated import pad_stamps

    cat = CosmosCatalog.load(folder)
    row = cat.table.iloc[int(np.random.default_rng(seed).integers(len(cat.table)))]
    sb, ps = place_at_redshift(
        cat.stamp(int(row["ident"])),
        float(row["pixel_scale"]),
        float(row["zphot"]),
        float(macro["z_source"][0]),
    )
    st, off = pad_stamps([sb], dtype=torch.float64)
    return R.PixelatedSources(stamps=st, pixel_scale=np.asarray([ps]), offsets=off)


def _case_numbers(geo, label, img, gamma, sheet, kap, sheet_centre="origin") -> StiffCase:
    """The row of one stiff case: arc, centre and total flux relative to the smooth model
    (``geo = (smooth, arc mask, centre slices, N_sub)``) and the summed subhalo κ with its
    sheet."""
    smooth, arc, centre, n_sub = geo
    km = float(kap.mean()) if kap is not None else 0.0
    ks = -km if sheet else 0.0
    return StiffCase(
        label,
        gamma,
        0 if kap is None else n_sub,
        sheet,
        float(img[arc].sum() / smooth[arc].sum()),
        float(img[centre].sum()),
        float(img.sum() / smooth.sum()),
        km,
        float(kap.min()) if kap is not None else 0.0,
        float(kap.max()) if kap is not None else 0.0,
        ks,
        km + ks,
        sheet_centre,
    )


def stiff_cases(
    psf,
    *,
    seed: int = 6,
    n_sub: int = 1500,
    gammas=(2.5, 1.2),
    sheets=(True, False),
    centres=("origin",),
    source: str = "sersic",
    cosmos_folder=None,
    settings: R.RenderSettings | None = None,
    macro: dict[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Render the stiff cases of one system; returns ``images`` (label → (H, W) numpy),
    ``cases`` (list of :class:`StiffCase`, first the smooth reference N_sub = 0),
    ``arc_mask``, ``macro``, ``subhalos`` (γ → population) and ``centre`` (row, col slices).

    ``source``: 'sersic' | 'multi_sersic' | 'cosmos' (a galaxy of ``cosmos_folder``).
    ``centres``: sheet centres rendered for every sheet-on case (``origin`` |
    ``mass_centroid``; labels of non-origin cases name the centre).
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
    smooth = (
        R.render_smooth(macro, psf, settings, sources=sources)[0].cpu().numpy().astype(np.float64)
    )
    frac = scene.subhalos.threshold_fraction
    arc = smooth > frac * smooth.max()
    n, d = settings.npix, settings.pixel_scale
    jc = int(round(macro["lens_y"][0] / d + (n - 1) / 2))
    ic = int(round(macro["lens_x"][0] / d + (n - 1) / 2))
    centre = (slice(jc - 2, jc + 3), slice(ic - 2, ic + 3))

    geo = (smooth, arc, centre, n_sub)
    images = {"smooth (N_sub = 0)": smooth}
    cases = [_case_numbers(geo, "smooth (N_sub = 0)", smooth, None, False, None)]
    pops = {}
    for gam in gammas:
        m = dict(macro, gamma_sub=np.array([float(gam)]))
        subs = _subhalos.sample_subhalos(
            scene, m, np.random.default_rng(seed + 1), smooth_images=smooth[None]
        )
        pops[gam] = subs
        kap = summed_subhalo_kappa(subs, n, d)
        for sheet, where in [(s, c) for s in sheets for c in (centres if s else ("origin",))]:
            ctx = contextlib.nullcontext() if sheet else sheet_off()
            with ctx:
                img = (
                    R.render(m, psf, settings, sources=sources, subhalos=subs, sheet_centre=where)[
                        0
                    ]
                    .cpu()
                    .numpy()
                    .astype(np.float64)
                )
            label = f"γ = {gam:g}, N_sub = {n_sub}, sheet {'on' if sheet else 'off'}"
            label += f" at {where.replace('_', ' ')}" if where != "origin" else ""
            images[label] = img
            cases.append(_case_numbers(geo, label, img, float(gam), sheet, kap, where))
    return {
        "images": images,
        "cases": cases,
        "arc_mask": arc,
        "macro": macro,
        "subhalos": pops,
        "centre": centre,
        "sources": sources,
        "settings": settings,
    }


def format_table(cases) -> str:
    """Markdown table of :class:`StiffCase` rows."""
    head = (
        "| case | arc flux / smooth | central 5×5 (e⁻/s) | total / smooth | mean Σκ_sub | "
        "min Σκ_sub | max Σκ_sub | κ_sheet | mean(Σκ_sub + sheet) "
        "|\n|---|---|---|---|---|---|---|---|---|"
    )
    rows = [
        f"| {c.label} | {c.arc_ratio:.3f} | {c.centre_flux:.4f} | {c.total_ratio:.3f} | "
        f"{c.kappa_mean:.3f} | "
        f"{c.kappa_min:.3f} | {c.kappa_max:.3f} | {c.kappa_sheet:.3f} | {c.kappa_total_mean:.1e} |"
        for c in cases
    ]
    return "\n".join([head, *rows])
