"""Accuracy budget of the default render settings on sampled scenes (not timed).

Budget (docs/performance.md): against a high-accuracy render of the same noise-free
image, max |Δ| ≤ 0.1 σ_noise (σ from ``instrument.noise_sigma_map`` of the reference)
and relative L2 ≤ 1e-3. ``tests/test_render.py`` checks the defaults on two synthetic
EPL populations; here the scenes come from the package's own samplers
(``simulation.macro.sample_macro``, ``subhalos.sample_subhalos`` on the arc / everywhere,
``los.sample_los_batch`` + ``los.los_profiles``), cover the NFW/tNFW CDM scenes (eager
population path) with NFW line-of-sight planes, the stiff γ → 1 end of the training
prior, and supersampling 2, so a later speed-up of any of these paths cannot silently
lose accuracy. The ``reference`` test compares the defaults with lenstronomy 1.14.2 on
small multi-plane scenes (:func:`subslope.validation.lenstronomy.lenstronomy_model`).
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from subslope.physics.instrument import gaussian_psf, load_empirical_psf
from subslope.render import pipeline as R
from subslope.validation import scenes as C
from subslope.validation.lenstronomy import lenstronomy_model
from tests.conftest import shared_data_dir

MAX_SIGMA, REL_L2 = 0.1, 1e-3
DEFAULT = R.RenderSettings(device="cpu")


pytestmark = pytest.mark.usefixtures("one_thread")


def _psf() -> torch.Tensor:
    """The empirical F814W PSF of the data folder, or a Gaussian where it is missing."""
    path = shared_data_dir() / "psf" / "emp_psf_f814w.fits"
    if path.is_file():
        return torch.as_tensor(load_empirical_psf(path))
    return torch.as_tensor(gaussian_psf(0.1, 0.04))


def _reference(s: R.RenderSettings) -> R.RenderSettings:
    return dataclasses.replace(
        s,
        dtype=torch.float64,
        n_terms=30,
        n_terms_main=30,
        compile="off",
        chunk_members=16,
        convolution="direct",
        population="direct",
    )


# (preset, N_sub, LoS, label γ, seed, settings overrides)
SCENES = {
    "train-nsub0-los": ("train", 0, True, None, 11, {}),
    "train-nsub1500-los": ("train", 1500, True, None, 12, {}),
    "train-nsub3000-los": ("train", 3000, True, None, 17, {}),
    "train-stiff-gamma1.1-nsub1500-los": ("train", 1500, True, 1.1, 13, {}),
    "train-nsub200-k2": ("train", 200, False, None, 14, {"supersample": 2}),
    "nfw-nsub600-los": ("nfw", 600, True, None, 15, {}),
    "tnfw-nsub600-los": ("tnfw", 600, True, None, 16, {}),
}


@pytest.mark.parametrize("key", list(SCENES))
def test_default_within_budget(key):
    kind, n_sub, los, gamma, seed, over = SCENES[key]
    batch = C.make_scene(_psf(), kind, 1, n_sub, los, seed=seed, gamma_label=gamma, delta_los=1.5)
    s = dataclasses.replace(DEFAULT, **over)
    img, ref = batch.render(s), batch.render(_reference(s))
    assert torch.isfinite(img).all()
    max_sigma, rel = C.image_errors(img, ref)
    print(f"{key}: max|Δ|/σ = {max_sigma:.2e}, rel L2 = {rel:.2e}")
    assert max_sigma <= MAX_SIGMA and rel <= REL_L2, (max_sigma, rel)


@pytest.mark.reference
@pytest.mark.parametrize("kind,n_sub", [("train", 40), ("tnfw", 40)])
def test_default_vs_lenstronomy_multiplane(kind, n_sub):
    """Defaults vs lenstronomy MultiPlane (per-slice sheets traced by lenstronomy)."""
    import warnings

    warnings.filterwarnings("ignore", message="Cosmology is provided")
    batch = C.make_scene(
        _psf(),
        kind,
        1,
        n_sub,
        True,
        seed=21,
        gamma_label=2.0 if kind == "train" else None,
        delta_los=1.5,
    )
    model = lenstronomy_model(batch.macro, batch.psf, 0, subhalos=batch.subhalos, los=batch.los)
    assert model.n_planes > 1
    theirs = torch.as_tensor(model.image())[None]
    max_sigma, rel = C.image_errors(batch.render(DEFAULT), theirs)
    _, rel64 = C.image_errors(batch.render(_reference(DEFAULT)), theirs)
    print(
        f"{kind}: default max|Δ|/σ = {max_sigma:.2e}, rel L2 = {rel:.2e}; float64 reference rel "
        f"L2 = {rel64:.2e}"
    )
    assert max_sigma <= MAX_SIGMA and rel <= REL_L2, (max_sigma, rel)
    assert rel64 <= 1e-5
