"""The workflow stages (subslope.stages) and the files they write, on small synthetic inputs."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from subslope.io.observations import find_lens_centre
from subslope.io.ratio_profiles import read_profiles, write_profiles
from subslope.plan import derived_seed
from subslope.stages.calibrate import (
    calibrate_stack_size,
    load_thresholds,
    summarize_coverage,
    threshold_for,
)
from subslope.stages.cdm_grid import cdm_band, measure_cdm_grid
from subslope.stages.figures import spearman_trend
from subslope.stages.null_tests import NULL_COLUMNS
from subslope.stages.null_tests.visibility import visibility_row
from subslope.stages.summary import SUMMARY_SECTIONS, write_summary
from subslope.stages.train import checkpoint_key, training_section
from subslope.stats import calibration as cal
from subslope.stats.calibration import safe_threshold
from subslope.stats.intervals import gamma_grid

SIGMA = 0.15  # per-image noise of the Gaussian toy


def _toy_profiles(gamma_true, grid, rng):
    """Exact log-likelihood-ratio profiles of x ~ N(γ, σ²): Wilks' theorem holds exactly."""
    x = gamma_true + SIGMA * rng.standard_normal(gamma_true.shape)
    return -((x[:, None] - grid[None, :]) ** 2) / (2 * SIGMA**2)


def _toy_file(path, n_sets, per_set, grid, rng, **extra):
    gam = np.repeat(rng.uniform(1.6, 2.4, n_sets), per_set)
    sets = np.repeat(np.arange(n_sets), per_set)
    write_profiles(
        path,
        log_ratio=_toy_profiles(gam, grid, rng),
        gammas=grid,
        gamma_true=gam,
        set_index=sets,
        theta_e=np.ones(gam.size),
        lens_x=np.zeros(gam.size),
        lens_y=np.zeros(gam.size),
        attrs={"scene": "toy", **extra},
    )
    return path


def test_profiles_round_trip(tmp_path, rng):
    grid = gamma_grid(1.1, 2.9, 19)
    lr = rng.normal(size=(6, 19))
    a = write_profiles(
        tmp_path / "a.h5",
        log_ratio=lr,
        gammas=grid,
        gamma_true=np.linspace(1.2, 2.8, 6),
        set_index=[0, 0, 1, 1, 2, 2],
        c_multiplier=None,
        theta_e=np.full(6, 1.1),
        lens_x=np.zeros(6),
        lens_y=np.zeros(6),
        attrs={"scene": "s", "meta": {"k": 1}},
    )
    b = write_profiles(
        tmp_path / "b.h5", log_ratio=lr[:2], gammas=grid, set_index=[0, 0], c_multiplier=[4.0, 4.0]
    )
    one = read_profiles(a)
    np.testing.assert_array_equal(one["log_ratio"], lr)
    np.testing.assert_array_equal(one["gammas"], grid)
    assert np.all(np.isnan(one["c_multiplier"])) and one["set_id"].tolist() == [0, 0, 1, 1, 2, 2]
    both = read_profiles([a, b])
    assert both["log_ratio"].shape == (8, 19)
    assert both["set_id"].tolist() == [0, 0, 1, 1, 2, 2, 3, 3]  # set ids distinct across files
    assert np.all(np.isnan(both["gamma_true"][6:])) and both["c_multiplier"][6:].tolist() == [
        4.0,
        4.0,
    ]
    write_profiles(tmp_path / "c.h5", log_ratio=lr[:, :5], gammas=grid[:5])
    with pytest.raises(ValueError, match="grid"):
        read_profiles([a, tmp_path / "c.h5"])
    with pytest.raises(ValueError, match="shape"):
        write_profiles(tmp_path / "d.h5", log_ratio=lr, gammas=grid[:5])


def test_calibrate_per_n_gaussian_toy(tmp_path):
    """Exact profiles: t(γ_true) ~ χ²₁ for every N, so τ_N ≈ 0.989 and coverage ≈ 0.68."""
    rng = np.random.default_rng(7)
    grid = gamma_grid(1.1, 2.9, 361)
    single = _toy_file(tmp_path / "single.h5", 600, 1, grid, rng)
    sets = _toy_file(tmp_path / "sets.h5", 300, 13, grid, rng)
    npzs = []
    for n, paths in ((1, [single]), (2, [sets]), (13, [sets])):
        out = calibrate_stack_size(paths, n, tmp_path / f"N{n}.npz", level=0.68, seed=3)
        assert out["tau_exact"]
        assert abs(out["tau"] - 0.989) < 0.3, (n, out["tau"])
        assert out["n_heldout"] > 0 and out["n_calibration"] > 0
        assert abs(out["coverage"] - 0.68) < 3 * out["coverage_err"] + 0.02, (n, out["coverage"])
        assert np.nanmax(np.abs(out["coverage_curve"] - out["levels"])) < 0.15
        npzs.append(tmp_path / f"N{n}.npz")
    assert np.load(tmp_path / "N13.npz")["t_true"].size == 300  # one stack per set
    assert np.load(tmp_path / "N2.npz")["t_true"].size == 300  # independent: one per set too
    disjoint = calibrate_stack_size([sets], 2, tmp_path / "D2.npz", seed=3, stacks="disjoint")
    assert disjoint["t_true"].size == 300 * 6  # six disjoint pairs per set of 13
    table, thr = summarize_coverage(
        npzs, tmp_path / "cal.csv", tmp_path / "thr.json", tmp_path / "coverage", run_name="toy"
    )
    assert table["n_images"].tolist() == [1, 2, 13]
    sigma = np.sqrt(0.68 * 0.32 * (1 / table["n_heldout"] + 1 / (table["n_calibration"] + 2)))
    assert np.allclose(table["coverage_sigma"], sigma)
    flagged = table["coverage"] < table["level"] - 2 * sigma
    assert table["overconfident"].tolist() == flagged.tolist()  # more than 2σ below the level
    assert (tmp_path / "coverage.png").stat().st_size > 10_000 and (
        tmp_path / "coverage.pdf"
    ).exists()
    loaded = load_thresholds(tmp_path / "thr.json")
    assert set(loaded["tau"]) == {1, 2, 13} and loaded["tau"][13] == pytest.approx(
        table["tau"].iloc[2]
    )
    assert threshold_for(loaded, 13) == (loaded["tau"][13], 13)
    assert threshold_for(loaded, 5) == (loaded["tau"][2], 2)  # not calibrated: largest N below
    # an over-confident estimator (ln r doubled): the empirical threshold still covers 68%
    data = read_profiles(sets)
    write_profiles(
        tmp_path / "over.h5",
        log_ratio=2 * data["log_ratio"],
        gammas=grid,
        gamma_true=data["gamma_true"],
        set_index=data["set_index"],
    )
    over = calibrate_stack_size([tmp_path / "over.h5"], 2, tmp_path / "over.npz", seed=3)
    assert abs(over["coverage"] - 0.68) < 3 * over["coverage_err"] + 0.02
    assert over["coverage_wilks"] < 0.6


def test_null_tests_tell_a_blind_estimator_from_one_that_reads_something(tmp_path):
    """Flat profiles (nothing read from the image): γ_MLE over the whole prior, a flat mean
    profile, no interval excludes part of the prior. Informative profiles (as the toy's
    χ²₁ ones): a curved mean for one γ, and most intervals exclude part of the prior."""
    import json

    import pandas as pd

    from subslope.stages.null_tests import null_tests

    rng = np.random.default_rng(11)
    grid = gamma_grid(1.1, 2.9, 181)
    n_sets, per = 40, 13
    gam = np.repeat(rng.uniform(1.1, 2.9, n_sets), per)
    sets = np.repeat(np.arange(n_sets), per)

    def profiles(name, log_ratio):
        return write_profiles(
            tmp_path / name, log_ratio=log_ratio, gammas=grid, gamma_true=gam, set_index=sets
        )

    blind = profiles("blind.h5", 1e-3 * rng.normal(size=(gam.size, grid.size)))  # flat
    # a γ read from something else than the subhalos: always 2.0
    seeing = profiles("seeing.h5", _toy_profiles(np.full(gam.size, 2.0), grid, rng))
    thr = tmp_path / "thresholds.json"
    taus = {"1": 1.0, "13": 1.0}
    thr.write_text(json.dumps({"level": 0.68, "wilks": 0.989, "tau": taus, "exact": {}}))
    table = null_tests(
        {"blind": [blind], "seeing": [seeing]},
        thr,
        tmp_path / "null.csv",
        tmp_path / "null",
        run_name="toy",
    ).set_index("scene")
    assert (
        table.loc["blind", "stack_excluding"] == 0 and table.loc["blind", "single_excluding"] == 0
    )
    assert table.loc["blind", "mean_profile_range"] < 0.01
    assert table.loc["blind", "n_stacks"] == n_sets and table.loc["blind", "n_per_stack"] == per
    assert table.loc["seeing", "stack_excluding"] > 0.9
    assert table.loc["seeing", "mean_profile_range"] > 1.0
    assert abs(table.loc["seeing", "stack_mle_p50"] - 2.0) < 0.05
    assert list(pd.read_csv(tmp_path / "null.csv")["scene"]) == ["blind", "seeing"]
    assert (tmp_path / "null.png").stat().st_size > 10_000


def test_safe_threshold_few_samples():
    assert safe_threshold([0.1, 0.5], 0.68) == (0.5, False)  # rank 3 > n = 2: max, flagged
    tau, exact = safe_threshold(np.arange(1.0, 101.0), 0.68)
    assert exact and tau == cal.threshold(np.arange(1.0, 101.0), 0.68)
    assert np.isnan(safe_threshold([], 0.68)[0])


def test_cdm_grid_and_set_stacks(tmp_path, rng):
    grid = gamma_grid(1.1, 2.9, 181)
    files = {}
    for scene, shift in (("nfw", 0.0), ("tnfw", 0.2)):
        for a in (1.0, 4.0):
            centre = 1.6 + 0.1 * np.log2(a) + shift
            gam = np.full(26, centre)
            lr = _toy_profiles(gam, grid, rng)
            path = write_profiles(
                tmp_path / f"{scene}_{a}.h5",
                log_ratio=lr,
                gammas=grid,
                set_index=np.repeat(np.arange(2), 13),
                c_multiplier=np.full(26, a),
            )
            files[(scene, a)] = [path]
    table = measure_cdm_grid(
        files, tmp_path / "g.npz", tmp_path / "g.csv", tmp_path / "fig4", run_name="toy"
    )
    assert len(table) == 4 and set(table["n_sets"]) == {2} and set(table["n_images"]) == {13}
    med = table.set_index(["scene", "multiplier"])["median"]
    assert med[("nfw", 1.0)] == pytest.approx(1.6, abs=0.1) and med[("tnfw", 4.0)] == pytest.approx(
        2.0, abs=0.1
    )
    assert np.load(tmp_path / "g.npz")["mles_tnfw"].shape == (2, 2)
    band = cdm_band(pd.read_csv(tmp_path / "g.csv"), "tnfw", 1.0)
    assert band[1] <= band[0] <= band[2]
    assert (tmp_path / "fig4.png").exists() and b"run_name=toy" in (
        tmp_path / "fig4.pdf"
    ).read_bytes()


@pytest.fixture(scope="module")
def simulated_lenses():
    """12 simulated validation images (lens light, arcs, subhalos, noise) with true centres."""
    from subslope import config as cfgmod
    from subslope.simulation import shard as simulate
    from tests.conftest import REPO_ROOT, shared_data_dir

    data = shared_data_dir()
    if not (data / "cosmos").is_dir():
        pytest.skip(f"no data mirror at {data}")
    cfg = cfgmod.load(REPO_ROOT / "config" / "tiny.yaml", env=False)
    cfg["data"]["resources_dir"] = str(data)
    out = simulate.simulate_images(cfg, "validation", 12, np.random.SeedSequence(99))
    return out["images"], out["params"]["lens_x"], out["params"]["lens_y"]


def test_lens_centre_on_simulated_images(simulated_lenses):
    images, lx, ly = simulated_lenses
    pix = 0.04
    miss = []
    for img, x0, y0 in zip(images, lx, ly):
        x, y = find_lens_centre(img, pixel_scale=pix)
        miss.append(np.hypot(x - x0, y - y0) / pix)
    # brief: 0.5 pixel. With the HST-like lens light of the campaign configs one image in
    # 12 (an arc as bright as the lens near its centre) is found 1.65 px off.
    assert np.sum(np.array(miss) < 0.25) >= 11 and max(miss) < 2.0, miss
    assert find_lens_centre(images[0], method="image_centre") == (0.0, 0.0)
    with pytest.raises(ValueError, match="method"):
        find_lens_centre(images[0], method="psf_fit")


def test_lens_centre_pixel_convention():
    """A symmetric blob centred between pixels: x_i = (i − (n−1)/2)·s, image[j, i] at (x_i, y_j)."""
    n, s = 100, 0.04
    xs = (np.arange(n) - (n - 1) / 2) * s
    xx, yy = np.meshgrid(xs, xs)
    img = np.exp(-((xx - 0.13) ** 2 + (yy + 0.07) ** 2) / (2 * 0.1**2))
    x, y = find_lens_centre(img, pixel_scale=s)
    assert x == pytest.approx(0.13, abs=0.004) and y == pytest.approx(-0.07, abs=0.004)


def test_spearman_trend():
    g = np.linspace(1.2, 2.8, 30)
    assert spearman_trend(g, g + 0.01 * np.sin(7 * g))["rho"] > 0.9
    assert np.isnan(spearman_trend(g[:2], g[:2])["rho"])


def test_summary_sections(tmp_path):
    hst = pd.DataFrame(
        [
            {
                "system": "SDSSJ0946+1006",
                "n_images": 1,
                "threshold_n": 1,
                "mle": 2.3,
                "lower": 1.9,
                "upper": 2.9,
                "threshold": 1.1,
                "lower_at_edge": False,
                "upper_at_edge": True,
                "multimodal": False,
            },
            {
                "system": "combined",
                "n_images": 13,
                "threshold_n": 13,
                "mle": 2.51,
                "lower": 2.47,
                "upper": 2.56,
                "threshold": 1.2,
                "lower_at_edge": False,
                "upper_at_edge": False,
                "multimodal": False,
            },
        ]
    )
    hst.to_csv(tmp_path / "intervals.csv", index=False)
    pd.DataFrame(
        [
            {
                "scene": "nfw",
                "multiplier": 1.0,
                "n_sets": 15,
                "n_images": 13,
                "median": 1.9,
                "lo": 1.8,
                "hi": 2.0,
            },
            {
                "scene": "tnfw",
                "multiplier": 1.0,
                "n_sets": 15,
                "n_images": 13,
                "median": 2.1,
                "lo": 2.0,
                "hi": 2.2,
            },
            {
                "scene": "nfw",
                "multiplier": 4.0,
                "n_sets": 15,
                "n_images": 13,
                "median": 2.2,
                "lo": 2.1,
                "hi": 2.3,
            },
        ]
    ).to_csv(tmp_path / "cdm.csv", index=False)
    pd.DataFrame(
        [
            {
                "n_images": n,
                "n_stacks": 100,
                "tau": 1.0,
                "tau_exact": True,
                "coverage": cov,
                "coverage_err": 0.05,
                "coverage_wilks": 0.6,
                "n_heldout": 50,
            }
            # N = 13: 2.5σ below 0.68 (σ of 50 calibration + 50 held-out stacks: 0.092)
            for n, cov in ((1, 0.7), (13, 0.45))
        ]
    ).to_csv(tmp_path / "cal.csv", index=False)
    rows = [
        visibility_row("nfw", np.linspace(1.2, 2.0, 30) + 0.1, np.linspace(1.2, 2.0, 30)),
        visibility_row("tnfw", np.full(30, 1.1), np.full(30, 1.1)),
    ]
    pd.DataFrame(rows).to_csv(tmp_path / "seen.csv", index=False)
    null = {c: 0.0 for c in NULL_COLUMNS}
    pd.DataFrame(
        [
            {**null, "scene": "null_nosub", "n_per_stack": 13, "stack_mle_p16": 1.1},
            {**null, "scene": "null_nosub_los", "n_per_stack": 13, "stack_mle_p16": 2.4},
        ]
    ).assign(stack_mle_p84=[1.7, 2.6]).to_csv(tmp_path / "null.csv", index=False)
    bench = tmp_path / "b.tsv"
    bench.write_text("s\th:m:s\tmax_rss\tmax_vms\n12.5\t0:00:12\t321.0\t900\n")
    out = write_summary(
        tmp_path / "out" / "summary.md",
        run_name="toy",
        config_hash="abc123",
        config_file="config/x.yaml",
        hst_csv=tmp_path / "intervals.csv",
        cdm_csv=tmp_path / "cdm.csv",
        calibration_csv=tmp_path / "cal.csv",
        visibility_csv=tmp_path / "seen.csv",
        null_csv=tmp_path / "null.csv",
        trend={"rho": 0.8, "p_value": 1e-5, "n": 20},
        benchmarks={"training": [bench], "hst": [tmp_path / "missing.tsv"]},
    )
    text = out.read_text()
    for section in SUMMARY_SECTIONS:
        assert f"## {section}" in text, section
    assert "abc123" in text and "2.510 (−0.040, +0.050)" in text and "ρ = 0.800" in text
    assert "**Over-confident at N = 13**: held-out coverage more than 2σ below" in text
    assert "moves the stack γ_MLE of nfw a = 1 by +0.100 ± 0.000" in text
    assert "**The subhalos of tnfw a = 1 are not seen by the estimator**" in text
    assert "null_nosub outside [1.10, 1.70]; null_nosub_los inside [2.40, 2.60]" in text
    assert (
        "γ_MLE = 2.51 is not a measurement of the subhalos' slope, because it lies inside the "
        "16–84% range of the subhalo-free null stacks (null_nosub_los [2.40, 2.60])."
    ) in text
    assert "`subslope seeds` trains it again" in text  # no table of trainings yet
    folder = out.parent
    res = pd.read_csv(folder / "hst_result.csv")
    assert res["gamma_mle"].iloc[0] == 2.51 and res["threshold_n"].iloc[0] == 13
    pred = pd.read_csv(folder / "cdm_prediction.csv").set_index("scene")
    assert pred.loc["nfw", "median"] == 1.9 and pred.loc["tnfw", "p84"] == 2.2
    assert len(pd.read_csv(folder / "coverage.csv")) == 2
    rt = pd.read_csv(folder / "stage_runtime.csv").set_index("stage")
    assert rt.loc["training", "seconds"] == 12.5 and rt.loc["training", "peak_rss_mb"] == 321.0
    assert rt.loc["hst", "jobs"] == 0
    # stages off: sections say so, the CSVs exist with headers only
    empty = write_summary(tmp_path / "e" / "summary.md", run_name="toy", config_hash="h")
    text = empty.read_text()
    assert "Stage `hst` not run" in text and "Stage `calibrate` not run" in text
    assert pd.read_csv(tmp_path / "e" / "cdm_visibility.csv").empty
    assert list(pd.read_csv(tmp_path / "e" / "hst_result.csv").columns)[:2] == [
        "n_images",
        "gamma_mle",
    ]


def test_training_section_and_checkpoint_key():
    from subslope import config as cfgmod

    cfg = cfgmod.validate({"seed": 5, "training": {"max_epochs": 3, "arch": {"width": 0.25}}})
    tr = training_section(cfg)
    assert tr["arch"] == {"preset": "reduced", "width": 0.25}
    assert tr["seed"] == derived_seed(5, "training") and tr["progress"] is False
    assert "device" not in tr and "gpus" not in tr and tr["pixel_scale"] == 0.04
    key = checkpoint_key(tr, ["a.h5"], ["v.h5"], {"train": "x"})
    assert key == checkpoint_key(
        {**tr, "max_epochs": 9}, ["a.h5"], ["v.h5"], {"train": "x"}
    )  # resume-safe
    assert key != checkpoint_key({**tr, "lr": 0.1}, ["a.h5"], ["v.h5"], {"train": "x"})
    assert key != checkpoint_key(tr, ["a.h5", "b.h5"], ["v.h5"], {"train": "x"})
    assert json.dumps(tr)  # JSON-able (Snakemake params)


def test_cli_has_campaign_commands(capsys):
    from subslope.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(
        [
            "train",
            "--config",
            "c.yaml",
            "--train",
            "a.h5",
            "b.h5",
            "--val",
            "v.h5",
            "--whitening",
            "w.json",
            "--out",
            "o",
        ]
    )
    assert args.train == ["a.h5", "b.h5"] and args.ckpt is None
    args = parser.parse_args(
        [
            "analyze-hst",
            "--config",
            "c.yaml",
            "--model",
            "m.pt",
            "--thresholds",
            "t.json",
            "--out",
            "o",
        ]
    )
    assert args.cdm is None and args.hst is None


def test_leave_one_out_names_the_lens_that_carries_the_stack():
    from subslope.stages.hst import leave_one_out

    g = np.linspace(1.1, 2.9, 91)
    centres = [2.0] * 5 + [2.8]
    profiles = np.array([-((g - c) ** 2) / 0.1 for c in centres])
    rows = leave_one_out([f"L{k}" for k in range(6)], profiles, g, 0.5, 5)
    shifts = {r["left_out"]: r["shift"] for r in rows}
    assert min(shifts, key=shifts.get) == "L5" and shifts["L5"] < -0.1
    assert all(abs(shifts[f"L{k}"]) < abs(shifts["L5"]) for k in range(5))
    assert all(r["n_images"] == 5 and r["lower"] <= r["mle"] <= r["upper"] for r in rows)


def test_cli_analyze_hst_passes_its_config_on(monkeypatch, tmp_path, capsys):
    """A light-subtracted estimator fits the cutouts' lens light with the config's PSF and
    detector: ``subslope analyze-hst --config`` hands that config to the stage."""
    import pandas as pd

    import subslope.stages.hst as hst_stage
    from subslope.cli import main
    from tests.conftest import REPO_ROOT

    seen = {}

    def fake(*args, **kwargs):
        seen.update(kwargs)
        return pd.DataFrame({"system": ["combined"]})

    monkeypatch.setattr(hst_stage, "analyze_hst", fake)
    argv = ["analyze-hst", "--config", str(REPO_ROOT / "config" / "tiny.yaml")]
    argv += ["--model", "m.pt", "--thresholds", "t.json", "--out", str(tmp_path)]
    assert main(argv) == 0, capsys.readouterr().err
    assert seen["config"]["run_name"] == "tiny"
    assert seen["loo_csv"] == tmp_path / "leave_one_out.csv"


def test_a_flipped_byte_in_a_profiles_file_is_an_error_naming_file_dataset_and_row(tmp_path):
    """Profiles files carry Fletcher-32 checksums: a corrupt log_ratio never reaches the
    calibration as a different number, and a truncated file is named."""
    from subslope.io.ratio_profiles import ProfilesError

    path = tmp_path / "p.h5"
    g = np.linspace(1.1, 2.9, 91)
    lr = np.random.default_rng(0).normal(size=(40, g.size))
    write_profiles(path, log_ratio=lr, gammas=g)
    np.testing.assert_array_equal(read_profiles(path)["log_ratio"], lr)
    import h5py

    with h5py.File(path, "r") as fh:
        offset = fh["log_ratio"].id.get_offset() or fh["log_ratio"].id.get_chunk_info(0).byte_offset
    raw = bytearray(path.read_bytes())
    raw[offset + 100] ^= 0xFF
    bad = tmp_path / "bad.h5"
    bad.write_bytes(bytes(raw))
    with pytest.raises(ProfilesError, match=rf"{bad}: log_ratio row \d+ cannot be read"):
        read_profiles(bad)
    cut = tmp_path / "cut.h5"
    cut.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(ProfilesError, match=f"{cut}"):
        read_profiles(cut)
