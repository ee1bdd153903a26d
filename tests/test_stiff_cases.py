"""Stiff cases of docs/simulation.md (subslope.validation.stiff): fast checks and a lenstronomy
cross-check."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from subslope.physics.instrument import gaussian_psf
from subslope.render import pipeline as R
from subslope.render import populations
from subslope.validation import stiff as D
from subslope.validation.lenstronomy import lenstronomy_model

PSF = gaussian_psf(0.1, 0.04)
COARSE = R.RenderSettings(
    npix=40, pixel_scale=0.1, device="cpu", dtype=torch.float64, compile="off", chunk_members=64
)


pytestmark = pytest.mark.usefixtures("one_thread")


def _record_sheets(monkeypatch):
    seen = []
    orig = R.population_pass

    def rec(*args, **kwargs):
        out = orig(*args, **kwargs)
        seen.append(float(out[2][0, 0]))
        return out

    monkeypatch.setattr(R, "population_pass", rec)
    return seen


@pytest.mark.parametrize("supersample", [1, 2])
def test_stiff_case_numbers_finite_and_sheet_cancels_mean(monkeypatch, supersample):
    psf = gaussian_psf(0.25, 0.1)
    s = dataclasses.replace(COARSE, supersample=supersample)
    seen = _record_sheets(monkeypatch)
    res = D.stiff_cases(psf, seed=6, n_sub=40, settings=s)
    cases = res["cases"]
    assert [c.gamma for c in cases] == [None, 2.5, 2.5, 1.2, 1.2]
    for c in cases:
        vals = [
            c.arc_ratio,
            c.centre_flux,
            c.total_ratio,
            c.kappa_mean,
            c.kappa_min,
            c.kappa_max,
            c.kappa_sheet,
        ]
        assert np.all(np.isfinite(vals)), c
    for img in res["images"].values():
        assert np.all(np.isfinite(img)) and img.shape == (40, 40)
    ref = cases[0]
    assert ref.arc_ratio == 1 and ref.total_ratio == 1
    # the renderer's sheet: minus the pixel-centre mean of the summed subhalo κ (also with
    # supersampling), so subhalos + sheet have zero mean over the image pixels
    sheets = iter(seen)
    for c in cases[1:]:
        if not c.sheet:
            next(sheets)  # sheet_off wraps the recorder: the renderer still computed it
            continue
        k_sheet = next(sheets)
        kap = D.summed_subhalo_kappa(res["subhalos"][c.gamma], s.npix, s.pixel_scale)
        assert abs(kap.mean() + k_sheet) < 1e-12 * kap.mean()
        assert abs(c.kappa_total_mean) < 1e-12 and k_sheet < 0
    assert cases[3].kappa_mean > cases[1].kappa_mean  # γ = 1.2 spreads more κ over the field


def test_sheet_off_is_a_local_diagnostic():
    res = D.stiff_cases(
        PSF, seed=3, n_sub=20, gammas=(1.2,), settings=dataclasses.replace(COARSE, pixel_scale=0.1)
    )
    on, off = (res["images"][c.label] for c in res["cases"][1:])
    assert not np.allclose(on, off)
    assert R.population_pass is populations.population_pass  # restored


@pytest.mark.reference
def test_gamma_1p2_against_lenstronomy():
    s = R.RenderSettings(
        device="cpu",
        dtype=torch.float64,
        compile="off",
        n_terms=30,
        n_terms_main=30,
        chunk_members=64,
    )
    res = D.stiff_cases(PSF, seed=6, n_sub=50, gammas=(1.2,), sheets=(True, False), settings=s)
    for c in res["cases"][1:]:
        m = dict(res["macro"], gamma_sub=np.array([1.2]))
        ref = lenstronomy_model(
            m, PSF, 0, subhalos=res["subhalos"][1.2], sheets=c.sheet, epl="EPL"
        ).image()
        rel = np.linalg.norm(res["images"][c.label] - ref) / np.linalg.norm(ref)
        print(f"{c.label}: relative L2 vs lenstronomy {rel:.1e}")
        assert rel <= 1e-3
