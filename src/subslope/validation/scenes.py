"""Sampled scenes for the accuracy tests and the benchmarks: a batch of images drawn by
the package's own samplers (:func:`make_scene`), one image of it (:func:`one_image`),
and the error of an image against a reference (:func:`image_errors`, in units of the
per-pixel noise σ and as a relative L2 norm)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from subslope.physics.instrument import noise_sigma_map
from subslope.render import pipeline as R
from subslope.simulation import los_halos, scenes
from subslope.simulation import subhalos as S
from subslope.simulation.macro import sample_macro

__all__ = ["Batch", "image_errors", "make_scene", "one_image"]


@dataclass
class Batch:
    """Parameters of ``n`` sampled images (what :func:`subslope.render.pipeline.render` takes)."""

    name: str
    macro: dict
    psf: torch.Tensor
    subhalos: S.SubhaloPopulation | None
    los: los_halos.LosPopulation | None

    @property
    def n(self) -> int:
        return len(self.macro["z_lens"])

    def render(self, settings: R.RenderSettings) -> torch.Tensor:
        return R.render(self.macro, self.psf, settings, subhalos=self.subhalos, los=self.los)


def make_scene(
    psf: torch.Tensor,
    kind: str = "train",
    n_img: int = 2,
    n_sub: int = 1500,
    with_los: bool = True,
    seed: int = 0,
    gamma_label: float | None = None,
    delta_los: float | None = 1.0,
    multiplier: float = 1.0,
    name: str | None = None,
) -> Batch:
    """``n_img`` images of scene preset ``kind`` ('train' | 'nfw' | 'tnfw') with N_sub
    fixed, seen through ``psf`` (a normalised kernel).

    Sérsic source (the COSMOS stamps are a separate knob), lens light, multipoles and
    shear on, subhalos from :func:`subslope.simulation.subhalos.sample_subhalos` (on the
    arc for train, everywhere for CDM), line-of-sight halos from
    :func:`subslope.simulation.los_halos.sample_los_batch` and
    :func:`subslope.simulation.los_halos.los_profiles` with δ_los fixed (1.0 = the mean
    of the prior U(0, 2); None draws it). ``gamma_label`` fixes the per-system label γ
    (train); ``multiplier`` the concentration multiplier of the CDM presets.
    """
    over = {
        "source": {"kind": "sersic"},
        "components": {"los": bool(with_los)},
        "images_per_set": 1,
    }
    scene = scenes.Scene.from_config(kind, over)
    rng = np.random.default_rng(seed)
    cdm = kind in ("nfw", "tnfw")
    macro = sample_macro(scene, n_img, rng, multiplier=multiplier if cdm else None)
    macro["n_sub"][:] = n_sub
    if gamma_label is not None and "gamma_sub" in macro:
        macro["gamma_sub"][:] = gamma_label
    if with_los and delta_los is not None:
        macro["delta_los"][:] = delta_los
    smooth = R.render_smooth(macro, psf, R.RenderSettings(compile="off", device="cpu")).numpy()
    subs = S.sample_subhalos(scene, macro, rng, smooth_images=smooth) if n_sub > 0 else None
    los = None
    if with_los:
        b = los_halos.sample_los_batch(
            macro["z_lens"],
            macro["z_source"],
            macro["theta_e"],
            macro["gamma_ml"],
            macro["delta_los"],
            rng,
        )
        los = los_halos.los_profiles(b, scene, macro, rng)
    if name is None:
        name = f"{kind} N_sub={n_sub}" + (" +LoS" if with_los else "")
    return Batch(name, macro, psf, subs, los)


def _slice_pop(pop, i: int):
    if pop is None:
        return None
    counts = np.asarray(pop.counts)
    off = np.concatenate([[0], np.cumsum(counts)])
    n = int(counts.sum())
    upd = {"counts": counts[i : i + 1]}
    for f in dataclasses.fields(pop):
        v = getattr(pop, f.name)
        if f.name != "counts" and isinstance(v, np.ndarray) and v.shape[:1] == (n,):
            upd[f.name] = v[off[i] : off[i + 1]]
    return dataclasses.replace(pop, **upd)


def one_image(batch: Batch, i: int) -> Batch:
    """Image ``i`` of a batch as a batch of one."""
    macro = {k: v[i : i + 1] for k, v in batch.macro.items()}
    return Batch(
        f"{batch.name} [{i}]",
        macro,
        batch.psf,
        _slice_pop(batch.subhalos, i),
        _slice_pop(batch.los, i),
    )


def image_errors(img: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """``(max |img − ref| / σ_noise(ref), ‖img − ref‖₂ / ‖ref‖₂)``, worst over the batch;
    σ_noise from :func:`subslope.physics.instrument.noise_sigma_map` of the reference."""
    img, ref = img.to(torch.float64), ref.to(torch.float64)
    d = img - ref
    max_sigma = float((d.abs() / noise_sigma_map(ref)).amax())
    rel = float((d.flatten(1).norm(dim=1) / ref.flatten(1).norm(dim=1)).max())
    return max_sigma, rel
