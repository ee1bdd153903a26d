"""Tests of the batched renderer (subslope.render.pipeline, subslope.physics.pairs.sums,
subslope.render.nearfar)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from subslope.physics.grid import pixel_grid
from subslope.physics.instrument import gaussian_psf, noise_sigma_map
from subslope.physics.light.pixelated import pad_stamps
from subslope.physics.light.sersic import magnitude_to_flux
from subslope.physics.profiles.epl import epl_convergence, epl_deflection
from subslope.render import counters, kernels, populations
from subslope.render import pipeline as R
from subslope.simulation.los_halos import LosPopulation
from subslope.simulation.subhalos import SubhaloPopulation

PSF = torch.as_tensor(gaussian_psf(0.1, 0.04))
FAST = R.RenderSettings(compile="off", chunk_members=64, device="cpu")


pytestmark = pytest.mark.usefixtures("one_thread")


# ------------------------------------------------------------------------- builders
def macro_of(
    b: int = 1, *, seed: int = 0, multipoles=True, shear=True, lens_light=True, sersic_source=True
) -> dict[str, np.ndarray]:
    g = np.random.default_rng(seed)
    u = lambda lo, hi: g.uniform(lo, hi, b)  # noqa: E731
    m = {
        "z_lens": u(0.15, 0.25),
        "z_source": u(0.5, 0.7),
        "src_x": u(-0.1, 0.1),
        "src_y": u(-0.1, 0.1),
        "src_rotation": u(-np.pi, np.pi),
        "lens_x": u(-0.2, 0.2),
        "lens_y": u(-0.2, 0.2),
        "theta_e": u(0.9, 1.3),
        "lens_e1": u(-0.2, 0.2),
        "lens_e2": u(-0.2, 0.2),
        "gamma_ml": np.clip(g.normal(2, 0.1, b), 1.1, 2.9),
    }
    if sersic_source:
        m.update(
            src_mag=u(20, 23),
            src_r=u(0.1, 0.4),
            src_n=u(0.8, 3),
            src_e1=u(-0.3, 0.3),
            src_e2=u(-0.3, 0.3),
        )
    if multipoles:
        m.update(a3=u(0, 0.05), phi3=u(-np.pi, np.pi), a4=u(0, 0.05), phi4=u(-np.pi, np.pi))
    if shear:
        m.update(shear_g1=u(-0.1, 0.1), shear_g2=u(-0.1, 0.1))
    if lens_light:
        m.update(
            light_mag=u(17, 19),
            light_r=np.abs(g.normal(0.8, 0.15, b)),
            light_n=np.clip(g.normal(2, 0.5, b), 0.5, 8),
            light_e1=u(-0.1, 0.1),
            light_e2=u(-0.1, 0.1),
        )
    return m


def subs_of(
    counts, *, seed=0, gamma=(1.5, 2.5), log_amp=(-3.0, -1.5), ring=True
) -> SubhaloPopulation:
    g = np.random.default_rng(seed)
    counts = np.asarray(counts, dtype=np.int64)
    n = int(counts.sum())
    r = g.uniform(0.9, 1.3, n) if ring else g.uniform(0, 2, n)
    phi = g.uniform(-np.pi, np.pi, n)
    return SubhaloPopulation(
        profile="epl",
        counts=counts,
        mass=np.full(n, 1e8),
        x=r * np.cos(phi),
        y=r * np.sin(phi),
        gamma=g.uniform(*gamma, n),
        e1=g.uniform(-0.2, 0.2, n),
        e2=g.uniform(-0.2, 0.2, n),
        amp=10 ** g.uniform(*log_amp, n),
    )


def los_of(counts, *, seed=0, zero=False) -> LosPopulation:
    g = np.random.default_rng(seed)
    counts = np.asarray(counts, dtype=np.int64)
    n = int(counts.sum())
    z = 0.015 + 0.01 * g.integers(0, 45, n)  # slice mid-redshifts < 0.5 <= z_source
    amp = np.zeros(n) if zero else 10 ** g.uniform(-3, -1.5, n)
    return LosPopulation(
        profile="epl",
        counts=counts,
        z=z,
        x=g.uniform(-2, 2, n),
        y=g.uniform(-2, 2, n),
        m200=np.full(n, 1e8),
        amp=amp,
        gamma=g.uniform(1.5, 2.5, n),
        e1=g.uniform(-0.2, 0.2, n),
        e2=g.uniform(-0.2, 0.2, n),
    )


def cosmos_like(b: int, seed=0) -> R.PixelatedSources:
    g = np.random.default_rng(seed)
    stamps = []
    for k in range(b):
        n = 40 + 7 * k
        yy, xx = np.mgrid[:n, :n] - (n - 1) / 2
        stamps.append(20.0 * np.exp(-(xx**2 + 2 * yy**2) / 60.0) * (1 + 0.2 * g.random((n, n))))
    st, off = pad_stamps(stamps, dtype=torch.float64)
    return R.PixelatedSources(stamps=st, pixel_scale=np.full(b, 0.012), offsets=off)


# ------------------------------------------------------------------------- basics
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_shapes_dtype_device(dtype):
    s = dataclasses.replace(FAST, dtype=dtype, npix=40)
    m = macro_of(3)
    img = R.render(m, PSF, s, subhalos=subs_of([5, 0, 9]))
    sm = R.render_smooth(m, PSF, s)
    for out in (img, sm):
        assert out.shape == (3, 40, 40) and out.dtype == dtype and out.device.type == "cpu"
        assert torch.isfinite(out).all()
    assert R.RenderSettings().device is None  # resolved at call time


def test_pixelated_source_and_supersampling():
    m = macro_of(2, sersic_source=False, lens_light=False)
    src = cosmos_like(2)
    s1 = dataclasses.replace(FAST, npix=50)
    s3 = dataclasses.replace(s1, supersample=3)
    a, b = R.render_smooth(m, PSF, s1, sources=src), R.render_smooth(m, PSF, s3, sources=src)
    assert a.shape == b.shape == (2, 50, 50)
    assert float(a.sum()) > 0
    # pixel integration changes the total flux little
    assert abs(float(a.sum() / b.sum()) - 1) < 0.02
    with pytest.raises(ValueError):
        R.render(macro_of(1), PSF, s1, sources=cosmos_like(1))  # both Sérsic keys and stamps


def test_finite_on_stiff_draws():
    m = macro_of(1, seed=3)
    s = dataclasses.replace(FAST, chunk_members=128)
    for gam in (1.01, 2.99):
        # N_sub = 3000: large (1e-1) to tiny (1e-12) amplitudes, some exactly on pixel centres
        subs = subs_of([3000], seed=4, gamma=(gam, gam), log_amp=(-12, -1), ring=False)
        subs.x[:50] = 0.02
        subs.y[:50] = 0.02
        img = R.render(m, PSF, s, subhalos=subs)
        assert torch.isfinite(img).all(), gam


# ------------------------------------------------------------------ instrumentation
def _boom(name):
    def f(*a, **k):
        raise AssertionError(f"{name} must not run")

    return f


def test_left_out_stages_are_not_evaluated(monkeypatch):
    m = macro_of(2, multipoles=False, shear=False, lens_light=False, sersic_source=False)
    for name in (
        "multi_plane_ray_shoot",
        "sersic_ellipse_from_magnitude",
        "population_pass",
        "shear_deflection",
        "multipole_deflections",
    ):
        monkeypatch.setattr(R, name, _boom(name))
    for name in ("split_pass", "member_table"):
        monkeypatch.setattr(populations, name, _boom(name))
    counters.reset_step_counts()
    img = R.render(
        m, PSF, FAST, sources=cosmos_like(2), subhalos=subs_of([0, 0]), los=los_of([0, 0])
    )
    assert torch.isfinite(img).all()
    c = counters.STEP_COUNTS
    # one batch of two images
    assert c["single_plane"] == 1 and c["main_lens"] == 1 and c["source_pixelated"] == 1
    for stage in (
        "multi_plane",
        "los",
        "subhalos",
        "split",
        "shear",
        "multipoles",
        "lens_light",
        "source_sersic",
        "supersample_bin",
    ):
        assert c[stage] == 0, stage


def test_stage_counts_when_on():
    counters.reset_step_counts()
    per_image = dataclasses.replace(FAST, batching="per_image")
    R.render(macro_of(2), PSF, per_image, subhalos=subs_of([3, 0]), los=los_of([2, 0]))
    c = counters.STEP_COUNTS
    # system 0: LoS -> multi-plane; system 1: nothing -> single plane, no population pass
    assert c["multi_plane"] == 1 and c["single_plane"] == 1
    assert c["subhalos"] == 1 and c["los"] >= 1
    assert c["shear"] == c["multipoles"] == c["lens_light"] == c["source_sersic"] == 2
    counters.reset_step_counts()  # one batch: one multi-plane trace with both systems
    R.render(macro_of(2), PSF, FAST, subhalos=subs_of([3, 0]), los=los_of([2, 0]))
    assert c["multi_plane"] == 1 and c["single_plane"] == 0 and c["shear"] == 1


# ------------------------------------------------------------------ determinism
def _split(m, subs, los, i):
    off_s, off_l = subs.offsets, np.concatenate([[0], np.cumsum(los.counts)])
    mi = {k: v[i : i + 1] for k, v in m.items()}
    si = dataclasses.replace(
        subs,
        counts=subs.counts[i : i + 1],
        **{
            k: getattr(subs, k)[off_s[i] : off_s[i + 1]]
            for k in ("mass", "x", "y", "gamma", "e1", "e2", "amp")
        },
    )
    li = dataclasses.replace(
        los,
        counts=los.counts[i : i + 1],
        **{
            k: getattr(los, k)[off_l[i] : off_l[i + 1]]
            for k in ("z", "x", "y", "m200", "amp", "gamma", "e1", "e2")
        },
    )
    return mi, si, li


def _batch_case():
    return macro_of(3, seed=5), subs_of([40, 0, 23], seed=6), los_of([3, 5, 0], seed=7)


@pytest.mark.parametrize("threads", [1, 2])
def test_per_image_batching_bit_identical(threads):
    """batching 'per_image': image i alone == image i of a render call, bit for bit."""
    torch.set_num_threads(threads)
    s = dataclasses.replace(FAST, chunk_members=16, npix=60, batching="per_image")
    m, subs, los = _batch_case()
    full = R.render(m, PSF, s, subhalos=subs, los=los)
    for i in range(3):
        mi, si, li = _split(m, subs, los, i)
        assert torch.equal(R.render(mi, PSF, s, subhalos=si, los=li)[0], full[i]), i


@pytest.mark.parametrize("batch_images", [2, 3])
def test_batched_default_matches_per_image(batch_images):
    """batching 'auto' (batches of batch_images; LoS slices of the images share planes by
    rank, one split pass per image): each image equals its render alone to float
    rounding, and the same batch gives the same bits twice."""
    s = R.RenderSettings(device="cpu", compile="off", batch_images=batch_images)
    m, subs, los = macro_of(3, seed=5), subs_of([140, 0, 90], seed=6), los_of([3, 5, 0], seed=7)
    full = R.render(m, PSF, s, subhalos=subs, los=los)
    assert torch.equal(full, R.render(m, PSF, s, subhalos=subs, los=los))
    for i in range(3):
        mi, si, li = _split(m, subs, los, i)
        alone = R.render(mi, PSF, s, subhalos=si, los=li)[0]
        assert float((alone - full[i]).abs().max()) <= 1e-5 * float(full[i].abs().max()), i


def test_sub_batched_path_matches():
    """The sub-batched (accelerator) path: padded slots, inactive planes and the plane
    union are exact no-ops mathematically. On CPU, SIMD main loops vs scalar tails of
    transcendental ops on the (b, w) parameter tensors change the last bit, so only
    float rounding is asserted here; bit identity is asserted on CUDA (test below)."""
    s = dataclasses.replace(FAST, chunk_members=16, batching="sub_batch")
    m, subs, los = _batch_case()
    full = R.render(m, PSF, s, subhalos=subs, los=los)
    for i in range(3):
        mi, si, li = _split(m, subs, los, i)
        alone = R.render(mi, PSF, s, subhalos=si, los=li)[0]
        assert float((alone - full[i]).abs().max()) <= 1e-5 * float(full[i].abs().max()), i


def test_sub_batched_split_matches():
    """The sub-batched (accelerator) path with the near/far split (populations of 140 and
    90 members, one system without subhalos, LoS planes): each image equals its
    per-image render to float64 rounding."""
    s = R.RenderSettings(device="cpu", compile="off", dtype=torch.float64, batching="sub_batch")
    m, subs, los = macro_of(3, seed=5), subs_of([140, 0, 90], seed=6), los_of([3, 5, 0], seed=7)
    counters.reset_step_counts()
    full = R.render(m, PSF, s, subhalos=subs, los=los)
    assert counters.STEP_COUNTS["split"] == 1
    per_image = dataclasses.replace(s, batching="per_image")
    for i in range(3):
        mi, si, li = _split(m, subs, los, i)
        alone = R.render(mi, PSF, per_image, subhalos=si, los=li)[0]
        assert float((alone - full[i]).abs().max()) <= 1e-12 * float(full[i].abs().max()), i


@pytest.mark.gpu
def test_batch_invariance_cuda():
    """Sub-batched CUDA path: an image alone and in a batch agree to float rounding."""
    s = dataclasses.replace(FAST, device="cuda", chunk_members=16)
    m, subs, los = _batch_case()
    full = R.render(m, PSF, s, subhalos=subs, los=los)
    assert full.device.type == "cuda"
    for i in range(3):
        mi, si, li = _split(m, subs, los, i)
        alone = R.render(mi, PSF, s, subhalos=si, los=li)[0]
        assert float((alone - full[i]).abs().max()) <= 1e-5 * float(full[i].abs().max()), i


def test_nsub_zero_equals_no_subhalos():
    m = macro_of(2, seed=8)
    a = R.render(m, PSF, FAST, subhalos=subs_of([0, 0]))
    b = R.render(m, PSF, FAST, subhalos=None)
    assert torch.equal(a, b)


# ------------------------------------------------------------------ physics
def test_kernel_and_negative_sheet():
    """Fused kernel == profiles.epl; population κ + sheet κ has zero mean over the pixels."""
    x, y = pixel_grid(100, 0.04, dtype=torch.float64)
    x, y = x.reshape(1, -1), y.reshape(1, -1)
    subs = subs_of([37], seed=9, gamma=(1.05, 2.95))
    pop = populations.pack_population(
        "epl",
        {k: getattr(subs, k) for k in ("amp", "gamma", "e1", "e2", "x", "y")},
        subs.counts,
        20,
        torch.float64,
        "cpu",
    )
    s64 = dataclasses.replace(FAST, dtype=torch.float64, n_terms=20)
    ax, ay, k_sheet = populations.population_pass(
        pop, x, y, s64, kernels.kernels_for(s64, torch.device("cpu")), 100 * 100
    )
    p = {
        k: torch.as_tensor(getattr(subs, k))[:, None]
        for k in ("amp", "gamma", "e1", "e2", "x", "y")
    }
    kap = epl_convergence(x, y, p["amp"], p["gamma"], p["e1"], p["e2"], p["x"], p["y"]).sum(0)
    assert abs(float(kap.mean() + k_sheet[0, 0])) < 1e-12 * float(kap.abs().mean())
    ex, ey = epl_deflection(
        x, y, p["amp"], p["gamma"], p["e1"], p["e2"], p["x"], p["y"], n_terms=20
    )
    ex, ey = ex.sum(0) + k_sheet[0] * x[0], ey.sum(0) + k_sheet[0] * y[0]
    scale = float(torch.hypot(ex, ey).max())
    assert float((ax[0] - ex).abs().max()) < 1e-12 * scale
    assert float((ay[0] - ey).abs().max()) < 1e-12 * scale


def test_multiplane_with_massless_los_equals_single_plane():
    s = dataclasses.replace(FAST, dtype=torch.float64)
    m = macro_of(2, seed=10)
    subs = subs_of([30, 12], seed=11)
    counters.reset_step_counts()
    a = R.render(m, PSF, s, subhalos=subs, los=los_of([6, 4], zero=True))
    assert counters.STEP_COUNTS["multi_plane"] == 1  # one batch of two
    b = R.render(m, PSF, s, subhalos=subs)
    assert float((a - b).abs().max()) < 1e-11 * float(b.abs().max())


def test_los_changes_image_and_rejects_planes_behind_source():
    m = macro_of(1, seed=12)
    a = R.render(m, PSF, FAST, los=los_of([8], seed=13))
    b = R.render(m, PSF, FAST)
    assert float((a - b).abs().max()) > 0
    bad = los_of([1])
    bad.z[:] = 0.95
    with pytest.raises(ValueError, match="z_source"):
        R.render(m, PSF, FAST, los=bad)


def test_sky_level_is_flat_after_the_psf_and_not_in_the_smooth_model():
    m = macro_of(2, seed=15)
    base = R.render(m, PSF, FAST)
    m["sky_level"] = np.array([0.1, 0.0])
    sky = R.render(m, PSF, FAST)
    torch.testing.assert_close(sky[0] - base[0], torch.full_like(base[0], 0.1))
    assert torch.equal(sky[1], base[1])
    assert torch.equal(
        R.render_smooth(m, PSF, FAST), R.render_smooth(macro_of(2, seed=15), PSF, FAST)
    )


def test_lens_light_flux_matches_magnitude():
    m = macro_of(1, seed=14)
    m.update(light_mag=np.array([18.0]), light_r=np.array([0.5]), light_n=np.array([1.5]))
    s = dataclasses.replace(FAST, npix=300, supersample=2, dtype=torch.float64)
    full, smooth = R.render(m, PSF, s), R.render_smooth(m, PSF, s)
    flux = float((full - smooth).sum())
    assert abs(flux / float(magnitude_to_flux(18.0)) - 1) < 2e-3


# ------------------------------------------------------------------ accuracy of the defaults
def _errors(img, ref):
    d = img.double() - ref
    return float((d.abs() / noise_sigma_map(ref)).max()), float(d.norm() / ref.norm())


@pytest.mark.parametrize("seed,n_sub,n_los", [(20, 1500, 12), (22, 3000, 0)])
def test_default_settings_error_budget(seed, n_sub, n_los):
    """Defaults (float32, n_terms, chunking, torch.compile if available) vs float64, n_terms=30."""
    m = macro_of(1, seed=seed)
    subs = subs_of([n_sub], seed=seed, gamma=(1.1, 2.9), log_amp=(-3.5, -1.0))
    los = los_of([n_los], seed=seed) if n_los else None
    default = R.RenderSettings(device="cpu")
    ref = dataclasses.replace(
        default, dtype=torch.float64, n_terms=30, n_terms_main=30, compile="off", chunk_members=64
    )
    img = R.render(m, PSF, default, subhalos=subs, los=los)
    img_ref = R.render(m, PSF, ref, subhalos=subs, los=los)
    max_sigma, rel = _errors(img[0], img_ref[0])
    assert max_sigma <= 0.1 and rel <= 1e-3, (max_sigma, rel)


# ------------------------------------------------------------------ lenstronomy
@pytest.mark.reference
def test_against_lenstronomy():
    """EPL + shear + multipoles + 6 EPL subhalos with their sheet, Sérsic source, float64:
    our image against lenstronomy's EPL model of the same parameters
    (:mod:`subslope.validation.lenstronomy`, the one adapter)."""
    from subslope.validation.lenstronomy import lenstronomy_model

    m = macro_of(1, seed=30, lens_light=False)
    m["src_rotation"][:] = 0.0
    subs = subs_of([6], seed=31, gamma=(1.6, 2.4), log_amp=(-2, -1.3))
    s = dataclasses.replace(FAST, dtype=torch.float64, n_terms=30, n_terms_main=30)
    ours = R.render(m, PSF, s, subhalos=subs)[0].numpy()
    model = lenstronomy_model(m, PSF.numpy(), 0, subhalos=subs, epl="EPL")
    assert model.n_planes == 1
    theirs = model.image()
    rel = np.linalg.norm(ours - theirs) / np.linalg.norm(theirs)
    print(f"lenstronomy rel L2 = {rel:.2e}")
    assert rel <= 1e-3


# ------------------------------------------------------------------ multi-Sérsic source
def multi_macro(b=3, seed=0, ncomp=None, kind_over=None):
    from subslope.simulation.macro import sample_macro
    from subslope.simulation.scenes import Scene

    over = {
        "source": {
            "kind": "multi_sersic",
            "r_sersic": {"dist": "uniform", "low": 0.1, "high": 0.2},
            "n_sersic": {"dist": "uniform", "low": 0.8, "high": 1.5},
        },
        "components": {"los": False, "subhalos": False, "lens_light": False},
    }
    if ncomp is not None:
        over["source"]["multi_sersic"] = {"n_components": ncomp}
    return sample_macro(Scene.from_config("train", over), b, np.random.default_rng(seed))


def test_multi_sersic_unlensed_flux_equals_total_magnitude():
    m = multi_macro(4, seed=3)
    for k in ("a3", "phi3", "a4", "phi4", "shear_g1", "shear_g2"):
        m.pop(k)
    m["theta_e"][:] = 1e-12  # main lens with negligible deflection: the source unlensed
    m["gamma_ml"][:] = 2.0
    s = dataclasses.replace(FAST, dtype=torch.float64, npix=160, pixel_scale=0.04, supersample=3)
    img = R.render(m, PSF, s)
    flux = img.sum((1, 2)).numpy()
    np.testing.assert_allclose(
        flux, magnitude_to_flux(torch.as_tensor(m["src_mag_total"])).numpy(), rtol=2e-3
    )
    assert set(m["src_ncomp"]) != {1}


def test_multi_sersic_components_off_are_not_evaluated(monkeypatch):
    import subslope.physics.light.sersic as LS

    calls = []
    orig = LS.sersic_ellipse_from_magnitude

    def spy(*a, **k):
        calls.append(1)
        return orig(*a, **k)

    monkeypatch.setattr(LS, "sersic_ellipse_from_magnitude", spy)
    m = multi_macro(3, seed=1)
    m["src_ncomp"][:] = [1, 3, 2]
    for j in range(4):  # the sampled fractions follow the count; rewrite them to match
        m[f"src_frac_{j}"][:] = [
            [1, 0.5, 0.6][i] * (j < m["src_ncomp"][i]) if j else [1, 0.5, 0.6][i] for i in range(3)
        ]
    counters.reset_step_counts()
    R.render(m, PSF, dataclasses.replace(FAST, batching="per_image"))
    assert counters.STEP_COUNTS["source_multi_sersic"] == 3
    assert counters.STEP_COUNTS["source_component"] == 1 + 3 + 2 == len(calls)
    assert counters.STEP_COUNTS["source_sersic"] == 0


def test_multi_sersic_one_component_equals_sersic_and_batch_invariance():
    m = multi_macro(3, seed=2, ncomp=1)
    single = {
        k: v
        for k, v in m.items()
        if not k.startswith("src_") or k in ("src_x", "src_y", "src_rotation")
    }
    single.update(
        src_mag=m["src_mag_total"],
        src_r=m["src_r_0"],
        src_n=m["src_n_0"],
        src_e1=m["src_e1_0"],
        src_e2=m["src_e2_0"],
    )
    assert torch.equal(R.render(m, PSF, FAST), R.render(single, PSF, FAST))
    m4 = multi_macro(3, seed=2)
    full = R.render(m4, PSF, FAST)
    one = R.render({k: v[1:2] for k, v in m4.items()}, PSF, FAST)
    assert float((full[1:2] - one).abs().max()) <= 1e-6 * float(one.abs().max())
    with pytest.raises(ValueError, match="exactly one source"):
        R.render(m4, PSF, FAST, sources=cosmos_like(3))
    bad = dict(m4)
    bad.pop("src_dx_2")
    with pytest.raises(ValueError, match="src_dx_2"):
        R.render(bad, PSF, FAST)
