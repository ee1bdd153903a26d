"""The one adapter to lenstronomy (1.14.2): the same parameters of one image as a
lenstronomy ``ImageModel``, for tests and benchmarks (a reference, never the engine).

The model: the main lens (``EPL_NUMBA``, or ``EPL``), SHEAR about the origin, two
MULTIPOLEs, the subhalos (EPL / NFW / TNFW) and a CONVERGENCE sheet in the lens plane,
one plane per line-of-sight slice with its own sheet (lenstronomy ``MultiPlane``,
Planck18, ``z_source_convention = z_source``), a SERSIC_ELLIPSE source and lens light,
the same PIXEL PSF. The negative sheets are computed with lenstronomy itself: the
pixel-centre rays are traced plane by plane with ``ray_shooting_partial_comoving`` and
the member convergences of each plane are averaged at those rays (the definition in
``docs/simulation.md``), so the sheet values are an independent check, not copied
from subslope. Importing this module does not import lenstronomy; calling it does.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from subslope.physics.instrument import NPIX, PIXEL_SCALE, ZERO_POINT
from subslope.physics.light.sersic import magnitude_to_flux, sersic_amp_from_flux
from subslope.ragged import counts_to_offsets

__all__ = [
    "LensModelUnrepresentable",
    "LenstronomyImage",
    "epl_theta_e",
    "members",
    "lenstronomy_model",
    "lenstronomy_noise",
]


class LensModelUnrepresentable(ValueError):
    """An EPL member whose θ_E = amp^(1/(γ−1)) underflows float64 (γ → 1, small amp)."""


def epl_theta_e(amp: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """lenstronomy's θ_E = amp^(1/(γ−1)) of EPL members (our amplitude parametrisation)."""
    log_te = np.log(amp) / (gamma - 1.0)
    if np.any(log_te < np.log(1e-300)):
        j = int(np.argmin(log_te))
        raise LensModelUnrepresentable(
            f"{int(np.sum(log_te < np.log(1e-300)))} EPL member(s) have θ_E < 1e-300 (e.g. amp "
            f"{amp[j]:.2e}, "
            f"γ {gamma[j]:.3f}): not representable in lenstronomy's θ_E parametrisation"
        )
    return np.exp(log_te)


def members(
    pop, lo: int, hi: int, sel=None, *, epl: str = "EPL_NUMBA"
) -> tuple[list[str], list[dict]]:
    """lenstronomy model names and kwargs of members ``lo:hi`` (optionally masked) of a
    population."""
    idx = np.arange(lo, hi) if sel is None else np.arange(lo, hi)[sel]
    if idx.size == 0:
        return [], []
    x, y = pop.x[idx], pop.y[idx]
    if pop.profile == "epl":
        te = epl_theta_e(pop.amp[idx], pop.gamma[idx])
        kw = [
            dict(
                theta_E=float(t),
                gamma=float(g),
                e1=float(a),
                e2=float(b),
                center_x=float(cx),
                center_y=float(cy),
            )
            for t, g, a, b, cx, cy in zip(te, pop.gamma[idx], pop.e1[idx], pop.e2[idx], x, y)
        ]
        return [epl] * idx.size, kw
    if pop.profile == "nfw":
        kw = [
            dict(Rs=float(r), alpha_Rs=float(a), center_x=float(cx), center_y=float(cy))
            for r, a, cx, cy in zip(pop.r_s[idx], pop.alpha_rs[idx], x, y)
        ]
        return ["NFW"] * idx.size, kw
    kw = [
        dict(
            Rs=float(r), alpha_Rs=float(a), r_trunc=float(t), center_x=float(cx), center_y=float(cy)
        )
        for r, a, t, cx, cy in zip(pop.r_s[idx], pop.alpha_rs[idx], pop.r_t[idx], x, y)
    ]
    return ["TNFW"] * idx.size, kw


@dataclass
class LenstronomyImage:
    """A lenstronomy ImageModel with its kwargs; ``image()`` is the noise-free render."""

    image_model: object
    kwargs: dict
    n_planes: int

    def image(self) -> np.ndarray:
        return self.image_model.image(**self.kwargs)


def _macro_lens(g: Mapping[str, float], epl: str) -> tuple[list[str], list[dict]]:
    """Main lens, shear about the origin and multipoles about the lens centre."""
    models = [epl]
    kw = [
        dict(
            theta_E=g["theta_e"],
            gamma=g["gamma_ml"],
            e1=g["lens_e1"],
            e2=g["lens_e2"],
            center_x=g["lens_x"],
            center_y=g["lens_y"],
        )
    ]
    if "shear_g1" in g:
        models.append("SHEAR")
        kw.append(dict(gamma1=g["shear_g1"], gamma2=g["shear_g2"], ra_0=0.0, dec_0=0.0))
    if "a3" in g:
        for m in (3, 4):
            models.append("MULTIPOLE")
            kw.append(
                dict(
                    m=m,
                    a_m=g[f"a{m}"],
                    phi_m=g[f"phi{m}"],
                    center_x=g["lens_x"],
                    center_y=g["lens_y"],
                )
            )
    return models, kw


@dataclass
class _Planes:
    """The lens models of one image, their redshifts, and per plane its members and the
    index of its sheet (``(z, member indices, sheet index)``)."""

    models: list[str]
    kw: list[dict]
    zlist: list[float]
    planes: list[tuple[float, list[int], int | None]]

    def add(self, z: float, names: list[str], kwargs: list[dict]) -> None:
        """Members ``names`` / ``kwargs`` and their (zero) sheet as a plane at ``z``."""
        idx = list(range(len(self.models), len(self.models) + len(names)))
        self.models += names + ["CONVERGENCE"]
        self.kw += kwargs + [dict(kappa=0.0, ra_0=0.0, dec_0=0.0)]
        self.zlist += [z] * (len(names) + 1)
        self.planes.append((z, idx, len(self.models) - 1))


def _image_planes(g: Mapping[str, float], i: int, subhalos, los, epl: str) -> _Planes:
    models, kw = _macro_lens(g, epl)
    zl = g["z_lens"]
    p = _Planes(models, kw, [zl] * len(models), [])
    if subhalos is not None and int(subhalos.counts[i]) > 0:
        off = counts_to_offsets(np.asarray(subhalos.counts))
        p.add(zl, *members(subhalos, off[i], off[i + 1], epl=epl))
    else:
        p.planes.append((zl, [], None))
    if los is not None and int(los.counts[i]) > 0:
        off = counts_to_offsets(np.asarray(los.counts))
        zh = los.z[off[i] : off[i + 1]]
        for zu in np.unique(zh):
            p.add(float(zu), *members(los, off[i], off[i + 1], zh == zu, epl=epl))
    return p


def _set_sheet(kw: dict, kap: np.ndarray, px: np.ndarray, py: np.ndarray, centre: str) -> None:
    """A plane's sheet: κ = −mean member κ at its rays ``px, py``, centred at the origin
    or (``mass_centroid``) at the κ-weighted centre of those rays."""
    kw["kappa"] = -float(np.mean(kap))
    if centre == "mass_centroid" and np.sum(kap) > 0:
        kw["ra_0"] = float(np.sum(kap * px) / np.sum(kap))
        kw["dec_0"] = float(np.sum(kap * py) / np.sum(kap))


def _lens_model(
    p: _Planes, zs: float, tx: np.ndarray, ty: np.ndarray, sheets: bool, centre: str = "origin"
):
    """The lenstronomy LensModel; with ``sheets``, each plane's sheet set to minus the mean
    member convergence at the pixel-centre rays on that plane (lenstronomy's own tracing),
    centred as ``centre`` says (:func:`_set_sheet`)."""
    from astropy.cosmology import Planck18
    from lenstronomy.LensModel.lens_model import LensModel

    models, kw = p.models, p.kw
    if len(p.planes) == 1:
        z, main, sheet = p.planes[0]
        if main and sheets:
            kap = LensModel([models[j] for j in main]).kappa(tx, ty, [kw[j] for j in main])
            _set_sheet(kw[sheet], kap, tx, ty, centre)
        return LensModel(models)
    lm = LensModel(
        models,
        z_source=zs,
        lens_redshift_list=p.zlist,
        multi_plane=True,
        cosmo=Planck18,
        z_source_convention=zs,
    )
    mpb = lm.lens_model.multi_plane_base
    cx, cy, ax, ay, z_prev = np.zeros_like(tx), np.zeros_like(ty), tx.copy(), ty.copy(), 0.0
    for z, on_plane, sheet in sorted(p.planes, key=lambda q: q[0]):
        if sheet is not None and sheets:
            dt = mpb._cosmo_bkg.T_xy(z_prev, z)
            tz = mpb._cosmo_bkg.T_xy(0.0, z)
            px, py = (cx + ax * dt) / tz, (cy + ay * dt) / tz
            kap = LensModel([models[j] for j in on_plane]).kappa(px, py, [kw[j] for j in on_plane])
            _set_sheet(kw[sheet], kap, px, py, centre)
        cx, cy, ax, ay = mpb.ray_shooting_partial_comoving(
            cx, cy, ax, ay, z_prev, z, kw, include_z_start=False
        )
        z_prev = z
    return lm


def _sersic_kwargs(g: Mapping[str, float]) -> tuple[dict, dict | None]:
    """The source (rotated by ``src_rotation``) and, when present, the lens light."""
    src = dict(
        amp=float(sersic_amp_from_flux(magnitude_to_flux(g["src_mag"]), g["src_r"], g["src_n"])),
        R_sersic=g["src_r"],
        n_sersic=g["src_n"],
        center_x=g["src_x"],
        center_y=g["src_y"],
    )
    c2, s2 = np.cos(2 * g["src_rotation"]), np.sin(2 * g["src_rotation"])
    src.update(e1=c2 * g["src_e1"] - s2 * g["src_e2"], e2=s2 * g["src_e1"] + c2 * g["src_e2"])
    if "light_mag" not in g:
        return src, None
    light = dict(
        amp=float(
            sersic_amp_from_flux(magnitude_to_flux(g["light_mag"]), g["light_r"], g["light_n"])
        ),
        R_sersic=g["light_r"],
        n_sersic=g["light_n"],
        e1=g["light_e1"],
        e2=g["light_e2"],
        center_x=g["lens_x"],
        center_y=g["lens_y"],
    )
    return src, light


def lenstronomy_model(
    macro: Mapping[str, np.ndarray],
    psf,
    i: int = 0,
    *,
    subhalos=None,
    los=None,
    npix: int = NPIX,
    pixel_scale: float = PIXEL_SCALE,
    sheets: bool = True,
    epl: str = "EPL_NUMBA",
    supersampling: int = 1,
    sheet_centre: str = "origin",
) -> LenstronomyImage:
    """lenstronomy 1.14.2 model of image ``i`` with exactly its parameters.

    ``macro``: per-image parameters (:func:`subslope.simulation.macro.sample_macro`, Sérsic
    source); ``psf``: the pixel kernel; ``subhalos`` / ``los``: ragged populations
    (:class:`subslope.simulation.subhalos.SubhaloPopulation`,
    :class:`subslope.simulation.los_halos.LosPopulation`); ``sheets``: each plane's negative
    sheet, computed by lenstronomy (off: a diagnostic); ``epl``: lenstronomy's EPL model
    (``EPL_NUMBA`` or ``EPL``); ``sheet_centre``: ``origin`` or ``mass_centroid``.
    """
    from lenstronomy.Data.imaging_data import ImageData
    from lenstronomy.Data.psf import PSF as LPSF
    from lenstronomy.ImSim.image_model import ImageModel
    from lenstronomy.LightModel.light_model import LightModel

    g = {k: float(np.asarray(v)[i]) for k, v in macro.items()}
    planes = _image_planes(g, i, subhalos, los, epl)
    x = (np.arange(npix) - (npix - 1) / 2) * pixel_scale
    xx, yy = np.meshgrid(x, x)
    lm = _lens_model(planes, g["z_source"], xx.ravel(), yy.ravel(), sheets, sheet_centre)
    src, light = _sersic_kwargs(g)
    kwargs = {"kwargs_lens": planes.kw, "kwargs_source": [src]}
    if light is not None:
        kwargs["kwargs_lens_light"] = [light]
    d = pixel_scale
    data = ImageData(
        image_data=np.zeros((npix, npix)),
        ra_at_xy_0=-(npix - 1) / 2 * d,
        dec_at_xy_0=-(npix - 1) / 2 * d,
        transform_pix2angle=np.array([[d, 0], [0, d]]),
    )
    lpsf = LPSF(psf_type="PIXEL", kernel_point_source=np.asarray(psf, dtype=np.float64))
    im = ImageModel(
        data,
        lpsf,
        lens_model_class=lm,
        source_model_class=LightModel(["SERSIC_ELLIPSE"]),
        lens_light_model_class=LightModel(["SERSIC_ELLIPSE"]) if light is not None else None,
        kwargs_numerics={"supersampling_factor": supersampling},
    )
    return LenstronomyImage(im, kwargs, len(planes.planes))


def lenstronomy_noise(instrument_seed: int = 0):
    """lenstronomy's SingleBand noise for the docs/physics.md instrument (for timing parity)."""
    from lenstronomy.SimulationAPI.observation_api import SingleBand

    band = SingleBand(
        pixel_scale=PIXEL_SCALE,
        exposure_time=2200.0,
        magnitude_zero_point=ZERO_POINT,
        read_noise=3.0,
        ccd_gain=1.58,
        sky_brightness=21.83,
        num_exposures=1,
        psf_type="NONE",
        data_count_unit="e-",
    )
    return band
