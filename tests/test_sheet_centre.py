"""Where a population's negative sheet is centred (``sheet_centre``: origin | mass_centroid).

The sheet centred at ``c`` deflects by ``κ_s (x − c)``; moving it from the origin to ``c``
adds the constant ``−κ_s c`` to the deflection everywhere, with ``c`` the κ-weighted centre
of the population over the pixel centres (computed here independently in float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.physics.grid import pixel_grid
from subslope.render import pipeline as R
from subslope.render.kernels import kernels_for
from subslope.render.populations import Geometry, Population, pack_population, population_pass
from subslope.render.tiles import GridBlock
from subslope.simulation.subhalos import SubhaloPopulation
from subslope.validation import stiff as D

pytestmark = pytest.mark.usefixtures("one_thread")

NPIX, PIX = 40, 0.1


def _population(n: int, gamma: float, centre=(0.6, -0.4), seed: int = 3) -> SubhaloPopulation:
    """``n`` EPL members scattered around ``centre`` (arcsec), one system."""
    rng = np.random.default_rng(seed)
    g = np.full(n, gamma)
    return SubhaloPopulation(
        profile="epl",
        counts=np.array([n]),
        mass=np.full(n, 1e8),
        x=centre[0] + rng.normal(0, 0.4, n),
        y=centre[1] + rng.normal(0, 0.4, n),
        gamma=g,
        e1=rng.uniform(-0.1, 0.1, n),
        e2=rng.uniform(-0.1, 0.1, n),
        amp=np.full(n, 0.005) ** (g - 1.0),
    )


def _pass(subs, settings, sheet_centre, x=None, y=None, members=True):
    xg, yg = pixel_grid(NPIX, PIX, dtype=torch.float64)
    xg, yg = xg.reshape(1, -1), yg.reshape(1, -1)
    flat = {k: getattr(subs, k) for k in ("amp", "gamma", "e1", "e2", "x", "y")}
    pop = pack_population(
        "epl", flat, subs.counts, settings.n_terms, torch.float64, "cpu", sheet_centre, members
    )
    geo = Geometry((GridBlock(0, NPIX, PIX),), 0, (xg, yg), displaced=False)
    px = xg if x is None else torch.cat([x, xg], 1)
    py = yg if y is None else torch.cat([y, yg], 1)
    kern = kernels_for(settings, torch.device("cpu"))
    return population_pass(pop, px, py, settings, kern, NPIX * NPIX, geo)


def _settings(population: str = "auto") -> R.RenderSettings:
    return R.RenderSettings(
        npix=NPIX,
        pixel_scale=PIX,
        device="cpu",
        dtype=torch.float64,
        compile="off",
        population=population,
    )


def _centroid64(subs) -> tuple[float, float, float]:
    kap = D.summed_subhalo_kappa(subs, NPIX, PIX)
    x, y = pixel_grid(NPIX, PIX, dtype=torch.float64)
    x, y = x.numpy(), y.numpy()
    return float(kap.mean()), float((kap * x).sum() / kap.sum()), float((kap * y).sum() / kap.sum())


@pytest.mark.parametrize("population", ["direct", "split"])
@pytest.mark.parametrize("gamma", [1.2, 2.5])
def test_centroid_sheet_adds_minus_kappa_times_centroid(population, gamma):
    subs = _population(300, gamma)
    s = _settings(population)
    ax0, ay0, k0 = _pass(subs, s, "origin")
    ax1, ay1, k1 = _pass(subs, s, "mass_centroid")
    kmean, cx, cy = _centroid64(subs)
    tol = 1e-6 if population == "direct" else 2e-4  # the split's far-field tolerance
    assert float(k1) == pytest.approx(-kmean, rel=tol)
    assert float(k1) == pytest.approx(float(k0), rel=1e-10)
    assert np.allclose((ax1 - ax0).numpy(), kmean * cx, rtol=tol, atol=1e-9)
    assert np.allclose((ay1 - ay0).numpy(), kmean * cy, rtol=tol, atol=1e-9)
    # on the population's side of the image; a flat γ → 1 population pulls it to the middle
    assert 0.02 < cx < 0.6 and -0.4 < cy < -0.01


def test_centroid_sheet_leaves_no_net_deflection_at_the_centre_of_a_symmetric_population():
    """A ring of identical circular members around ``c``: the population deflects by 0 at
    ``c`` (symmetry), so the net deflection there is the sheet's alone: ``κ̄ |c|`` centred
    at the origin, ``κ̄ |c − c_img|`` at the centroid ``c_img`` over the (finite) image."""
    c = np.array([0.5, -0.3])
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    n = phi.size
    subs = SubhaloPopulation(
        profile="epl",
        counts=np.array([n]),
        mass=np.full(n, 1e8),
        x=c[0] + 0.4 * np.cos(phi),
        y=c[1] + 0.4 * np.sin(phi),
        gamma=np.full(n, 2.5),
        e1=np.zeros(n),
        e2=np.zeros(n),
        amp=np.full(n, 0.1**1.5),
    )
    s = _settings("direct")
    at = torch.tensor([[c[0]]], dtype=torch.float64), torch.tensor([[c[1]]], dtype=torch.float64)
    net = {}
    for where in ("origin", "mass_centroid"):
        ax, ay, k = _pass(subs, s, where, *at)
        net[where] = float(np.hypot(float(ax[0, 0]), float(ay[0, 0])))
    kmean, cx, cy = _centroid64(subs)
    assert net["origin"] == pytest.approx(kmean * np.hypot(*c), rel=1e-6)
    assert net["mass_centroid"] == pytest.approx(kmean * np.hypot(c[0] - cx, c[1] - cy), rel=1e-6)
    assert net["mass_centroid"] < 0.5 * net["origin"]


def test_empty_and_zero_kappa_populations_give_the_origin_and_no_nan():
    subs = _population(5, 2.0)
    s = _settings()
    flat = {k: getattr(subs, k) * 0 for k in ("amp",)}
    flat.update({k: getattr(subs, k) for k in ("gamma", "e1", "e2", "x", "y")})
    pop = pack_population(
        "epl", flat, subs.counts, s.n_terms, torch.float64, "cpu", "mass_centroid"
    )
    xg, yg = pixel_grid(NPIX, PIX, dtype=torch.float64)
    xg, yg = xg.reshape(1, -1), yg.reshape(1, -1)
    ax, ay, k = population_pass(pop, xg, yg, s, kernels_for(s, torch.device("cpu")), NPIX**2)
    assert torch.all(torch.isfinite(ax)) and torch.all(ax == 0) and float(k) == 0.0


def test_the_scene_schema_and_the_renderer_know_the_same_sheet_centres():
    from subslope.config import load_schema
    from subslope.render.populations import SHEET_CENTRES
    from subslope.simulation import scenes

    assert scenes.SHEET_CENTRES == SHEET_CENTRES  # twin kept for torch-free planning
    props = load_schema()["$defs"]["scene"]["properties"]
    for block in ("subhalos", "los"):
        assert tuple(props[block]["properties"]["sheet_centre"]["enum"]) == SHEET_CENTRES


def test_unknown_sheet_centre_is_refused_naming_the_choices():
    with pytest.raises(ValueError, match="origin.*mass_centroid"):
        Population("epl", torch.zeros(1, 7, 1), np.array([1]), "centre")
    with pytest.raises(ValueError, match="sheet_centre"):
        R.render({}, torch.ones(1, 1), R.RenderSettings(), sheet_centre="middle")


def test_lenstronomy_reference_agrees_with_the_centroid_sheet():
    pytest.importorskip("lenstronomy")
    from subslope.physics.instrument import gaussian_psf
    from subslope.validation.lenstronomy import lenstronomy_model

    psf = gaussian_psf(0.1, 0.04)
    s = R.RenderSettings(device="cpu", dtype=torch.float64, compile="off")
    res = D.stiff_cases(
        psf,
        seed=6,
        n_sub=150,
        gammas=(1.2,),
        sheets=(True,),
        centres=("origin", "mass_centroid"),
        settings=s,
    )
    case = res["cases"][-1]
    assert case.sheet_centre == "mass_centroid"
    m = dict(res["macro"], gamma_sub=np.array([1.2]))
    ref = lenstronomy_model(
        m, psf.numpy(), 0, subhalos=res["subhalos"][1.2], epl="EPL", sheet_centre="mass_centroid"
    ).image()
    ours = res["images"][case.label]
    assert np.linalg.norm(ours - ref) / np.linalg.norm(ref) < 1e-3
    origin = res["images"][res["cases"][-2].label]
    assert np.linalg.norm(origin - ref) / np.linalg.norm(ref) > 10 * np.linalg.norm(
        ours - ref
    ) / np.linalg.norm(ref)
