"""Shared helpers of the performance benchmarks and of tests/test_accuracy_budget.py.

- :func:`make_scene`: a batch of sampled scenes (train / nfw / tnfw presets, Sérsic
  source, fixed N_sub, optional LoS) through the package's own samplers;
- the lenstronomy reference model of the same parameters is
  :func:`subslope.validation.lenstronomy.lenstronomy_model` (the one adapter);
- :func:`image_errors`, :func:`reference_settings`, :func:`psf_kernel` are re-exported
  from ``benchmarks/render_speed.py`` (one definition of the error metrics).
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

from subslope.render import pipeline as R  # noqa: E402
from subslope.simulation import los as los_mod  # noqa: E402
from subslope.simulation import scenes  # noqa: E402
from subslope.simulation import subhalos as S  # noqa: E402
from subslope.simulation.macro import sample_macro  # noqa: E402

psf_kernel = _rs.psf_kernel
image_errors = _rs.image_errors
reference_settings = _rs.reference_settings

__all__ = [
    "Batch",
    "make_scene",
    "one_image",
    "psf_kernel",
    "image_errors",
    "reference_settings",
    "machine_info",
    "load",
]


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
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "lenstronomy": lv,
        "uptime": up,
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.is_available(),
    }


# ----------------------------------------------------------------------------- scenes
@dataclass
class Batch:
    """Parameters of ``n`` sampled images (what :func:`subslope.render.pipeline.render` takes)."""

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


def make_scene(
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
    """``n_img`` images of scene preset ``kind`` ('train' | 'nfw' | 'tnfw') with N_sub fixed.

    Sérsic source (the COSMOS stamps are a separate knob), lens light, multipoles and
    shear on, subhalos from :func:`subslope.simulation.subhalos.sample_subhalos` (on the arc for
    train, everywhere for CDM), LoS from :func:`subslope.simulation.los.sample_los_batch` +
    :func:`subslope.simulation.los.los_profiles` with δ_los fixed (1.0 = the mean of the prior
    U(0, 2); None draws it). ``gamma_label`` fixes the per-system label γ (train).
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
    psf = psf_kernel()
    smooth = R.render_smooth(macro, psf, R.RenderSettings(compile="off", device="cpu")).numpy()
    subs = S.sample_subhalos(scene, macro, rng, smooth_images=smooth) if n_sub > 0 else None
    los = None
    if with_los:
        b = los_mod.sample_los_batch(
            macro["z_lens"],
            macro["z_source"],
            macro["theta_e"],
            macro["gamma_ml"],
            macro["delta_los"],
            rng,
        )
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
