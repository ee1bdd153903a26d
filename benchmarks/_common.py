"""Shared helpers of the performance benchmarks and of tests/test_accuracy_budget.py.

- :func:`make_scene`: a batch of sampled scenes (train / nfw / tnfw presets, Sérsic
  source, fixed N_sub, optional LoS) through the package's own samplers;
- :func:`lenstronomy_model`: the *same* parameters of one image as a lenstronomy 1.14.2
  ``ImageModel`` (benchmark/test-only reference, never the engine): EPL_NUMBA main
  lens, SHEAR about the origin, two MULTIPOLEs, EPL_NUMBA / NFW / TNFW subhalos and a
  CONVERGENCE sheet in the lens plane, one plane per LoS slice with its own sheet
  (lenstronomy ``MultiPlane``, Planck18, ``z_source_convention = z_source``),
  SERSIC_ELLIPSE source and lens light, the same PIXEL PSF, supersampling 1;
- :func:`image_errors`, :func:`reference_settings`, :func:`psf_kernel` are re-exported
  from ``benchmarks/render_speed.py`` (one definition of the error metrics).

The negative sheets of lenstronomy's model are computed with lenstronomy itself: the
pixel-centre rays are traced plane by plane with ``ray_shooting_partial_comoving`` and
the member convergences of each plane are averaged at those rays (the definition in
``docs/simulation.md``), so the sheet values are an independent check, not copied
from subslope.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import render_speed as _rs  # noqa: E402  (reuse: PSF, error metrics, reference settings)

from subslope import los as los_mod  # noqa: E402
from subslope import render as R  # noqa: E402
from subslope import scenes  # noqa: E402
from subslope import subhalos as S  # noqa: E402
from subslope.light.sersic import magnitude_to_flux, sersic_amp_from_flux  # noqa: E402

psf_kernel = _rs.psf_kernel
image_errors = _rs.image_errors
reference_settings = _rs.reference_settings

__all__ = ["Batch", "make_scene", "one_image", "lenstronomy_model", "LensModelUnrepresentable",
           "psf_kernel", "image_errors", "reference_settings", "machine_info", "load"]


def load() -> str:
    """1/5/15-minute load average, formatted."""
    return "{:.2f}/{:.2f}/{:.2f}".format(*os.getloadavg())


def machine_info() -> dict:
    cpu = "unknown"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import lenstronomy
        lv = lenstronomy.__version__
    except ImportError:  # pragma: no cover
        lv = "not installed"
    try:
        up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:  # pragma: no cover
        up = load()
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "torch": torch.__version__, "lenstronomy": lv, "uptime": up,
            "torch_threads": torch.get_num_threads(), "cuda": torch.cuda.is_available()}


# ----------------------------------------------------------------------------- scenes
@dataclass
class Batch:
    """Parameters of ``n`` sampled images (what :func:`subslope.render.render` takes)."""

    name: str
    macro: dict
    psf: torch.Tensor
    subhalos: S.SubhaloPopulation | None
    los: los_mod.LosPopulation | None

    @property
    def n(self) -> int:
        return len(self.macro["z_lens"])

    def render(self, settings: R.RenderSettings) -> torch.Tensor:
        return R.render(self.macro, self.psf, settings, subhalos=self.subhalos, los=self.los)


def make_scene(kind: str = "train", n_img: int = 2, n_sub: int = 1500, with_los: bool = True, seed: int = 0,
               gamma_label: float | None = None, delta_los: float | None = 1.0, multiplier: float = 1.0,
               name: str | None = None) -> Batch:
    """``n_img`` images of scene preset ``kind`` ('train' | 'nfw' | 'tnfw') with N_sub fixed.

    Sérsic source (the COSMOS stamps are a separate knob), lens light, multipoles and
    shear on, subhalos from :func:`subslope.subhalos.sample_subhalos` (on the arc for
    train, everywhere for CDM), LoS from :func:`subslope.los.sample_los_batch` +
    :func:`subslope.los.los_profiles` with δ_los fixed (1.0 = the mean of the prior
    U(0, 2); None draws it). ``gamma_label`` fixes the per-system label γ (train).
    """
    over = {"source": {"kind": "sersic"}, "components": {"los": bool(with_los)}, "images_per_set": 1}
    scene = scenes.Scene.from_config(kind, over)
    rng = np.random.default_rng(seed)
    cdm = kind in ("nfw", "tnfw")
    macro = scenes.sample_macro(scene, n_img, rng, multiplier=multiplier if cdm else None)
    macro["n_sub"][:] = n_sub
    if gamma_label is not None and "gamma_sub" in macro:
        macro["gamma_sub"][:] = gamma_label
    if with_los and delta_los is not None:
        macro["delta_los"][:] = delta_los
    psf = psf_kernel()
    smooth = R.render_smooth(macro, psf, R.RenderSettings(compile="off", device="cpu")).numpy()
    subs = S.sample_subhalos(scene, macro, rng, smooth_images=smooth) if n_sub > 0 else None
    los = None
    if with_los:
        b = los_mod.sample_los_batch(macro["z_lens"], macro["z_source"], macro["theta_e"], macro["gamma_ml"],
                                     macro["delta_los"], rng)
        los = los_mod.los_profiles(b, scene, macro, rng)
    if name is None:
        name = f"{kind} N_sub={n_sub}" + (" +LoS" if with_los else "")
    return Batch(name, macro, psf, subs, los)


def _slice_pop(pop, i: int):
    if pop is None:
        return None
    counts = np.asarray(pop.counts)
    off = np.concatenate([[0], np.cumsum(counts)])
    n = int(counts.sum())
    upd = {"counts": counts[i:i + 1]}
    for f in dataclasses.fields(pop):
        v = getattr(pop, f.name)
        if f.name != "counts" and isinstance(v, np.ndarray) and v.shape[:1] == (n,):
            upd[f.name] = v[off[i]:off[i + 1]]
    return dataclasses.replace(pop, **upd)


def one_image(batch: Batch, i: int) -> Batch:
    """Image ``i`` of a batch as a batch of one."""
    macro = {k: v[i:i + 1] for k, v in batch.macro.items()}
    return Batch(f"{batch.name} [{i}]", macro, batch.psf, _slice_pop(batch.subhalos, i), _slice_pop(batch.los, i))


# ------------------------------------------------------------------------ lenstronomy
class LensModelUnrepresentable(ValueError):
    """An EPL member whose θ_E = amp^(1/(γ−1)) underflows float64 (γ → 1, small amp)."""


def _epl_theta_e(amp: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    log_te = np.log(amp) / (gamma - 1.0)
    if np.any(log_te < np.log(1e-300)):
        j = int(np.argmin(log_te))
        raise LensModelUnrepresentable(
            f"{int(np.sum(log_te < np.log(1e-300)))} EPL member(s) have θ_E < 1e-300 (e.g. amp {amp[j]:.2e}, "
            f"γ {gamma[j]:.3f}): not representable in lenstronomy's θ_E parametrisation")
    return np.exp(log_te)


def _members(pop, lo: int, hi: int, sel=None) -> tuple[list[str], list[dict]]:
    """lenstronomy model names and kwargs of members ``lo:hi`` (optionally masked) of a population."""
    idx = np.arange(lo, hi) if sel is None else np.arange(lo, hi)[sel]
    if idx.size == 0:
        return [], []
    x, y = pop.x[idx], pop.y[idx]
    if pop.profile == "epl":
        te = _epl_theta_e(pop.amp[idx], pop.gamma[idx])
        kw = [dict(theta_E=float(t), gamma=float(g), e1=float(a), e2=float(b), center_x=float(cx), center_y=float(cy))
              for t, g, a, b, cx, cy in zip(te, pop.gamma[idx], pop.e1[idx], pop.e2[idx], x, y)]
        return ["EPL_NUMBA"] * idx.size, kw
    if pop.profile == "nfw":
        kw = [dict(Rs=float(r), alpha_Rs=float(a), center_x=float(cx), center_y=float(cy))
              for r, a, cx, cy in zip(pop.r_s[idx], pop.alpha_rs[idx], x, y)]
        return ["NFW"] * idx.size, kw
    kw = [dict(Rs=float(r), alpha_Rs=float(a), r_trunc=float(t), center_x=float(cx), center_y=float(cy))
          for r, a, t, cx, cy in zip(pop.r_s[idx], pop.alpha_rs[idx], pop.r_t[idx], x, y)]
    return ["TNFW"] * idx.size, kw


@dataclass
class LenstronomyImage:
    """A lenstronomy ImageModel with its kwargs; ``image()`` is the noise-free render."""

    image_model: object
    kwargs: dict
    n_planes: int

    def image(self) -> np.ndarray:
        return self.image_model.image(**self.kwargs)


def lenstronomy_model(batch: Batch, i: int = 0, npix: int = 100, pixel_scale: float = 0.04) -> LenstronomyImage:
    """lenstronomy 1.14.2 model of image ``i`` of ``batch`` with exactly its parameters."""
    from astropy.cosmology import Planck18
    from lenstronomy.Data.imaging_data import ImageData
    from lenstronomy.Data.psf import PSF as LPSF
    from lenstronomy.ImSim.image_model import ImageModel
    from lenstronomy.LensModel.lens_model import LensModel
    from lenstronomy.LightModel.light_model import LightModel

    g = {k: float(v[i]) for k, v in batch.macro.items()}
    zl, zs = g["z_lens"], g["z_source"]
    models = ["EPL_NUMBA"]
    kw = [dict(theta_E=g["theta_e"], gamma=g["gamma_ml"], e1=g["lens_e1"], e2=g["lens_e2"],
               center_x=g["lens_x"], center_y=g["lens_y"])]
    if "shear_g1" in g:
        models.append("SHEAR")
        kw.append(dict(gamma1=g["shear_g1"], gamma2=g["shear_g2"], ra_0=0.0, dec_0=0.0))
    if "a3" in g:
        for m in (3, 4):
            models.append("MULTIPOLE")
            kw.append(dict(m=m, a_m=g[f"a{m}"], phi_m=g[f"phi{m}"], center_x=g["lens_x"], center_y=g["lens_y"]))
    zlist = [zl] * len(models)
    planes: list[tuple[float, list[int], int | None]] = []  # (z, member indices, sheet index)
    main_members: list[int] = []
    subs = batch.subhalos
    if subs is not None and int(subs.counts[i]) > 0:
        off = np.concatenate([[0], np.cumsum(subs.counts)])
        m_, k_ = _members(subs, off[i], off[i + 1])
        main_members = list(range(len(models), len(models) + len(m_)))
        models += m_ + ["CONVERGENCE"]
        kw += k_ + [dict(kappa=0.0, ra_0=0.0, dec_0=0.0)]
        zlist += [zl] * (len(m_) + 1)
    planes.append((zl, main_members, len(models) - 1 if main_members else None))
    los = batch.los
    if los is not None and int(los.counts[i]) > 0:
        off = np.concatenate([[0], np.cumsum(los.counts)])
        zh = los.z[off[i]:off[i + 1]]
        for zu in np.unique(zh):
            m_, k_ = _members(los, off[i], off[i + 1], zh == zu)
            idx = list(range(len(models), len(models) + len(m_)))
            models += m_ + ["CONVERGENCE"]
            kw += k_ + [dict(kappa=0.0, ra_0=0.0, dec_0=0.0)]
            zlist += [float(zu)] * (len(m_) + 1)
            planes.append((float(zu), idx, len(models) - 1))
    multi = len(planes) > 1
    x = (np.arange(npix) - (npix - 1) / 2) * pixel_scale
    xx, yy = np.meshgrid(x, x)
    tx, ty = xx.ravel(), yy.ravel()
    if multi:
        lm = LensModel(models, z_source=zs, lens_redshift_list=zlist, multi_plane=True, cosmo=Planck18,
                       z_source_convention=zs)
        mpb = lm.lens_model.multi_plane_base
        # sheets: trace the pixel-centre rays plane by plane (lenstronomy's own stepping)
        cx, cy, ax, ay, z_prev = np.zeros_like(tx), np.zeros_like(ty), tx.copy(), ty.copy(), 0.0
        for z, members, sheet in sorted(planes, key=lambda p: p[0]):
            if sheet is not None:
                dt = mpb._cosmo_bkg.T_xy(z_prev, z)
                tz = mpb._cosmo_bkg.T_xy(0.0, z)
                px, py = (cx + ax * dt) / tz, (cy + ay * dt) / tz
                kap = LensModel([models[j] for j in members]).kappa(px, py, [kw[j] for j in members])
                kw[sheet]["kappa"] = -float(np.mean(kap))
            cx, cy, ax, ay = mpb.ray_shooting_partial_comoving(cx, cy, ax, ay, z_prev, z, kw,
                                                               include_z_start=False)
            z_prev = z
    else:
        lm = LensModel(models)
        if main_members:
            kap = LensModel([models[j] for j in main_members]).kappa(tx, ty, [kw[j] for j in main_members])
            kw[planes[0][2]]["kappa"] = -float(np.mean(kap))
    src = dict(amp=float(sersic_amp_from_flux(magnitude_to_flux(g["src_mag"]), g["src_r"], g["src_n"])),
               R_sersic=g["src_r"], n_sersic=g["src_n"], center_x=g["src_x"], center_y=g["src_y"])
    c2, s2 = np.cos(2 * g["src_rotation"]), np.sin(2 * g["src_rotation"])
    src.update(e1=c2 * g["src_e1"] - s2 * g["src_e2"], e2=s2 * g["src_e1"] + c2 * g["src_e2"])
    kwargs = {"kwargs_lens": kw, "kwargs_source": [src]}
    light = None
    if "light_mag" in g:
        light = LightModel(["SERSIC_ELLIPSE"])
        kwargs["kwargs_lens_light"] = [dict(
            amp=float(sersic_amp_from_flux(magnitude_to_flux(g["light_mag"]), g["light_r"], g["light_n"])),
            R_sersic=g["light_r"], n_sersic=g["light_n"], e1=g["light_e1"], e2=g["light_e2"],
            center_x=g["lens_x"], center_y=g["lens_y"])]
    d = pixel_scale
    data = ImageData(image_data=np.zeros((npix, npix)), ra_at_xy_0=-(npix - 1) / 2 * d,
                     dec_at_xy_0=-(npix - 1) / 2 * d, transform_pix2angle=np.array([[d, 0], [0, d]]))
    psf = LPSF(psf_type="PIXEL", kernel_point_source=np.asarray(batch.psf, dtype=np.float64))
    im = ImageModel(data, psf, lens_model_class=lm, source_model_class=LightModel(["SERSIC_ELLIPSE"]),
                    lens_light_model_class=light, kwargs_numerics={"supersampling_factor": 1})
    return LenstronomyImage(im, kwargs, len(planes))


def lenstronomy_noise(instrument_seed: int = 0):
    """lenstronomy's SingleBand noise for the SCIENCE.md §2 instrument (for timing parity)."""
    from lenstronomy.SimulationAPI.observation_api import SingleBand

    band = SingleBand(pixel_scale=0.04, exposure_time=2200.0, magnitude_zero_point=25.127, read_noise=3.0,
                      ccd_gain=1.58, sky_brightness=21.83, num_exposures=1, psf_type="NONE",
                      data_count_unit="e-")
    return band
