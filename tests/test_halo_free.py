"""The halo-free null test (subslope.stages.null_tests.halo_free): the sheets-only render, the label
trend and its bounds, the bias by N_sub, and the verdict on estimators that do and do
not read γ from something other than the halos."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from subslope.io.ratio_profiles import write_profiles
from subslope.physics.grid import pixel_grid
from subslope.stages.null_tests.halo_free import (
    label_trend,
    nsub_bias,
    partial_spearman,
    sheet_channel,
    variant_row,
)
from subslope.stats.intervals import gamma_grid
from tests.test_sheet_centre import _centroid64, _pass, _population, _settings

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.parametrize("population", ["direct", "split"])
@pytest.mark.parametrize("centre", ["origin", "mass_centroid"])
def test_sheets_only_pass_is_the_analytic_sheet(population, centre):
    """``members=False``: the deflection of the population's negative sheet alone,
    ``−κ̄ (x − c)`` with κ̄ the members' mean convergence over the image (float64
    reference) and ``c`` the origin or their κ-weighted centre; the sheet is the one
    the full pass adds."""
    subs = _population(200, 2.2)
    s = _settings(population)
    ax, ay, k = _pass(subs, s, centre, members=False)
    ax_full, ay_full, k_full = _pass(subs, s, centre)
    kmean, cx, cy = _centroid64(subs)
    if centre == "origin":
        cx = cy = 0.0
    x, y = (v.reshape(1, -1).numpy() for v in pixel_grid(40, 0.1, dtype=torch.float64))
    tol = 1e-6 if population == "direct" else 2e-4
    assert float(k) == float(k_full) == pytest.approx(-kmean, rel=tol)
    scale = tol * kmean * float(np.max(np.abs(x)))
    np.testing.assert_allclose(ax.numpy(), -kmean * (x - cx), rtol=tol, atol=scale)
    np.testing.assert_allclose(ay.numpy(), -kmean * (y - cy), rtol=tol, atol=scale)
    assert float(torch.max(torch.abs(ax_full - ax))) > 0.1 * float(torch.max(torch.abs(ax)))


def test_label_trend_of_a_copy_a_constant_and_noise():
    rng = np.random.default_rng(0)
    label = rng.uniform(1.1, 2.9, 200)
    same = label_trend(label, 0.5 * label + 1.0)
    assert same["rho"] == pytest.approx(1.0) and same["slope"] == pytest.approx(0.5)
    assert same["se"] == pytest.approx(0.0, abs=1e-12)
    flat = label_trend(label, np.full(200, 2.9))
    assert flat["rho"] == 0.0 and flat["p"] == 1.0 and flat["slope"] == pytest.approx(0, abs=1e-15)
    blind = label_trend(label, rng.uniform(1.1, 2.9, 200))
    assert blind["bound"] == pytest.approx(2 / math.sqrt(199))
    assert abs(blind["rho"]) < blind["bound"] and abs(blind["slope"]) < 2 * blind["se"]
    with pytest.raises(ValueError, match="at least 3"):
        label_trend([1.0, 2.0], [1.0, 2.0])


def test_nsub_bias_bins_every_image_once_and_measures_a_known_bias():
    rng = np.random.default_rng(1)
    n_sub = rng.integers(0, 120, 1000)
    gamma = rng.uniform(1.1, 2.9, 1000)
    rows = nsub_bias(n_sub, gamma, gamma + 0.1 + 0.001 * n_sub, n_bins=4)
    assert sum(r["n_images"] for r in rows) == 1000 and len(rows) == 4
    assert rows[0]["n_sub_lo"] == 0 and rows[-1]["n_sub_hi"] == n_sub.max()
    for lo, hi in zip(rows[:-1], rows[1:]):
        assert hi["n_sub_lo"] == lo["n_sub_hi"] + 1
    for r in rows:
        mid = 0.1 + 0.001 * 0.5 * (r["n_sub_lo"] + r["n_sub_hi"])
        assert r["bias_mean"] == pytest.approx(mid, abs=0.01)
        assert r["bias_p16"] <= r["bias_p50"] <= r["bias_p84"]


def _profiles_reading(label, rng, strength):
    """Quadratic ln r̂ peaked at ``strength·label + (1 − strength)·noise``."""
    g = gamma_grid()
    peak = strength * label + (1 - strength) * rng.uniform(1.1, 2.9, label.size)
    return g, -((g[None, :] - peak[:, None]) ** 2) / 0.5


def test_the_verdict_fails_an_estimator_that_reads_the_label_without_halos():
    rng = np.random.default_rng(2)
    sets = np.repeat(np.arange(200), 13)
    label = np.repeat(rng.uniform(1.1, 2.9, 200), 13)
    g, blind = _profiles_reading(label, rng, 0.0)
    _, leaky = _profiles_reading(label, rng, 0.3)
    ok = variant_row("sheets_kept", g, blind, label, sets)
    bad = variant_row("sheets_removed", g, leaky, label, sets)
    assert ok["passes"] is True and ok["n_stacks"] == 200 and ok["n_images"] == 2600
    assert bad["passes"] is False and bad["rho_stack"] > 0.5
    assert variant_row("original", g, leaky, label, sets)["passes"] == ""


def test_halo_free_null_refuses_too_few_sets(tmp_path):
    from subslope.stages.null_tests.halo_free import halo_free_null

    g = gamma_grid()
    path = write_profiles(
        tmp_path / "p.h5",
        log_ratio=np.zeros((4, g.size)),
        gammas=g,
        gamma_true=np.ones(4),
        set_index=np.array([0, 0, 1, 1]),
    )
    with pytest.raises(ValueError, match="null_tests.halo_free_sets = 5.*only 2 sets"):
        halo_free_null([path], {}, [], tmp_path / "a.csv", tmp_path / "b.csv", n_sets=5)


def test_partial_spearman_removes_what_the_given_variables_explain():
    rng = np.random.default_rng(5)
    z1, z2 = rng.normal(size=(2, 500))
    x = z1 + 0.5 * z2 + 0.1 * rng.normal(size=500)
    y = z1 + z2 + 0.1 * rng.normal(size=500)
    from scipy.stats import spearmanr

    assert spearmanr(x, y)[0] > 0.8
    assert abs(partial_spearman(x, y, [z1, z2])) < 0.2
    w = rng.normal(size=500)
    assert partial_spearman(x + w, y + w, [z1, z2]) > 0.5  # a shared part the z do not explain
    assert partial_spearman(z1, y, [z1]) == 0.0


def test_sheet_channel_tells_the_sheet_amplitude_from_another_channel():
    """Sheets that follow the label; a kept-sheet γ_MLE that reads only the sheets passes
    the partial test, one that also reads the label beyond them does not."""
    rng = np.random.default_rng(6)
    label = rng.uniform(1.1, 2.9, 300)
    sheets = {
        "subhalos": -np.exp(-(label - 1.0)) + 0.05 * rng.normal(size=300),
        "los": -0.3 * np.exp(-(label - 1.0)) + 0.05 * rng.normal(size=300),
    }
    reads_sheets = 2.0 - sheets["subhalos"] - sheets["los"] + 0.5 * rng.normal(size=300)
    rows = sheet_channel(label, sheets, reads_sheets)
    by = {(r["quantity"], r["against"]): r for r in rows}
    assert by[("sheet_kappa_subhalos", "label")]["rho"] > 0.9
    assert not by[("sheet_kappa_los", "label")]["within"]
    last = rows[-1]
    assert last["given"] == "sheet_kappa_subhalos + sheet_kappa_los"
    assert last["within"] and last["bound"] == pytest.approx(2 / math.sqrt(300 - 1 - 7))
    leaky = reads_sheets + 2.0 * (label - label.mean()) * rng.uniform(0.8, 1.2, 300)
    assert not sheet_channel(label, sheets, leaky)[-1]["within"]
    # a population absent from the scene (zero sheets) is left out
    none = sheet_channel(label, {"subhalos": sheets["subhalos"], "los": np.zeros(300)}, leaky)
    assert none[-1]["given"] == "sheet_kappa_subhalos" and len(none) == 3


def test_sheet_channel_with_fewer_stacks_than_regressors_has_no_partial_row():
    label = np.array([1.2, 1.9, 2.5, 2.8])
    rows = sheet_channel(label, {"subhalos": -1 / label, "los": -0.1 / label**2}, label)
    assert [r["given"] for r in rows] == [""] * 4


@pytest.mark.slow
def test_a_shard_made_on_cuda_re_renders_on_this_machine(tiny_run, tmp_path, monkeypatch):
    """The re-renders take dtype and knobs from the shard but render on a device this
    job has: a shard whose settings say CUDA re-renders on a CPU-only node, to the same
    images as with its settings saying CPU."""
    import json
    import shutil

    import h5py

    from subslope.io.shards import open_shard
    from subslope.simulation.rerender import stored_settings, subhalo_free_images

    if torch.cuda.is_available():
        pytest.skip("needs a machine without CUDA")
    monkeypatch.chdir(tiny_run.parent)  # the shard names its COSMOS folders relative to it
    shard = tmp_path / "cuda_made.h5"
    shutil.copyfile(tiny_run / "simulate_shard" / "nfw" / "a1" / "shard_0.h5", shard)
    with h5py.File(shard, "r+") as fh:
        settings = json.loads(fh.attrs["render_settings"])
        settings["device"] = "cuda:0"
        fh.attrs["render_settings"] = json.dumps(settings)
    with open_shard(shard) as opened:
        assert stored_settings(opened.attrs).device is None  # this job's device
    images = subhalo_free_images(shard, [0, 1])
    same = subhalo_free_images(tiny_run / "simulate_shard" / "nfw" / "a1" / "shard_0.h5", [0, 1])
    assert np.array_equal(images, same) and np.isfinite(images).all()
