"""The Snakemake workflow: lint, dry runs (job counts per rule, stage switches, reruns),
config errors, a real run of fetch + gallery and ONE real run of the whole tiny campaign
(module-scoped fixture) whose outputs several tests inspect.

Every run happens in a private copy of the workflow under a temporary folder (so tests
never touch the repository's results/ or lock it), with the data mirror passed through
the SUBSLOPE_DATA_MIRROR environment variable.
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from subslope.campaigns.targets import SUMMARY_CSVS
from subslope.figures.gallery import log_stretch_limits
from tests.conftest import REPO_ROOT, TINY
from tests.conftest import run_snakemake as snakemake

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")


def test_lint_clean(workdir):
    proc = snakemake(workdir, "--lint")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Lints for" not in proc.stdout + proc.stderr


def test_dry_run_reduced_campaign_job_counts(workdir, data_dir):
    """config/config.yaml: one job per shard, per evaluated shard and per N, one of the rest."""
    from subslope import config as cfgmod

    cfg = cfgmod.load(workdir / "config" / "config.yaml", env=False)
    proc = snakemake(workdir, "-n", mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    stats = _job_stats(proc.stdout)
    sim = cfg["simulation"]["scenes"]
    n_mult = len(cfg["simulation"]["multipliers"])
    null = cfg["null_tests"]["scenes"]
    cdm = cfg["cdm"]
    controls = [*cdm["field_controls"], *cdm["reference_controls"]]
    grids = ("nfw", "tnfw", "nfw_ref", "tnfw_ref")
    extra = cdm["extra_scenes"] + [s for s in cdm["abundance"] if s not in grids]
    per_mult = {
        s: len(sim[s].get("multipliers") or cfg["simulation"]["multipliers"]) for s in extra
    }
    assert stats["simulate_shard"] == sum(
        sim[s]["n_shards"] for s in ("train", "validation", "test_epl", *null, *controls)
    )
    n_grid = n_mult * sum(sim[s]["n_shards"] for s in grids)
    n_extra = sum(per_mult[s] * sim[s]["n_shards"] for s in extra)
    assert stats["simulate_cdm_shard"] == n_grid + n_extra
    assert stats["evaluate_profiles"] == sum(
        sim[s]["n_shards"] for s in ("validation", "test_epl", *null, *controls)
    )
    assert stats["evaluate_cdm_profiles"] == stats["simulate_cdm_shard"]
    # every multiplier of the grids and the extra scenes (not the abundance series)
    n_free = n_grid + sum(per_mult[s] * sim[s]["n_shards"] for s in cdm["extra_scenes"])
    assert stats["subhalo_free_profiles"] == n_free
    assert stats["calibrate_threshold"] == len(cfg["calibration"]["n_images"]) == 6
    # shard 0 of train, test_epl, the nulls and the controls
    assert stats["signal_budget"] == 2 + len(null) + len(controls)
    assert stats["signal_budget_cdm"] == 4 * n_mult + sum(per_mult.values())
    assert stats["fetch_data"] == 21  # one job per registered data file
    for rule in (
        "plot_hst_gallery",
        "compute_whitening",
        "train_estimator",
        "plot_training_curves",
        "summarize_coverage",
        "effective_slope",
        "measure_cdm_grid",
        "null_tests",
        "cdm_visibility",
        "analyze_hst",
        "plot_validation",
        "summarize_signal_budget",
        "write_summary",
        "all",
    ):
        assert stats[rule] == 1, (rule, stats)
    for rule in ("measure_epl_control", "measure_abundance", "concentration_contrast"):
        assert stats[rule] == 1, (rule, stats)
    assert stats["plot_scene_examples"] == len(sim)
    assert "results/evaluate_profiles/nfw/a0.5/shard_0.h5" in proc.stdout
    assert "results/calibrate_threshold/N13.npz" in proc.stdout
    assert "results/checkpoints" not in proc.stdout  # never a declared output
    off = _stages(workdir, False, False)
    proc = snakemake(workdir, "-n", "--configfile", str(off), mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    assert "fetch_data" in proc.stdout and "plot_hst_gallery" not in proc.stdout
    assert "simulate_shard" not in proc.stdout and "train_estimator" not in proc.stdout


def test_bad_config_stops_before_any_job(workdir, data_dir):
    bad = workdir / "config" / "bad.yaml"
    bad.write_text("instrument:\n  pixel_scale: 5.0\ndata:\n  mirorr: /x\n")
    proc = snakemake(workdir, "--cores", "1", "--configfile", str(bad), mirror=data_dir)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "instrument.pixel_scale" in out and "(0, 1.0]" in out
    assert "data.mirorr" in out
    assert not (workdir / "resources").exists() and not (workdir / "results").exists()


STAGES = (
    "gallery",
    "simulate",
    "train",
    "evaluate",
    "calibrate",
    "cdm_grid",
    "null_tests",
    "hst",
    "figures",
    "summary",
)


def _stages(workdir: Path, gallery: bool, simulate: bool, **more: bool) -> str:
    """A config file switching stages (later stages default to `simulate`'s value)."""
    flags = {"gallery": gallery, "simulate": simulate}
    flags.update({s: more.get(s, simulate) for s in STAGES[2:]})
    name = "stages_" + "".join(str(int(flags[s])) for s in STAGES)
    path = workdir / "config" / f"{name}.yaml"
    path.write_text(
        "base: config.yaml\nstages:\n"
        + "".join(f"  {k}: {str(v).lower()}\n" for k, v in flags.items())
    )
    return str(path)


@pytest.mark.slow
def test_real_run_fetch_and_gallery(workdir, data_dir):
    gallery_only = ("--configfile", _stages(workdir, True, False))
    proc = snakemake(
        workdir, "--cores", "2", *gallery_only, "--config", "run_name=pytest_run", mirror=data_dir
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    png = workdir / "results" / "figures" / "hst_gallery.png"
    pdf = workdir / "results" / "figures" / "hst_gallery.pdf"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000
    assert pdf.read_bytes()[:5] == b"%PDF-"
    assert b"run_name=pytest_run" in pdf.read_bytes() and b"run_name=pytest_run" in png.read_bytes()
    resources = workdir / "resources"
    assert len(list((resources / "hst").glob("*.npy"))) == 13
    assert (resources / "psf" / "emp_psf_f814w.fits").is_file()
    assert not any(p.is_symlink() for p in resources.rglob("*"))  # copies, not links
    log = (workdir / "logs" / "plot_hst_gallery.log").read_text()
    assert "loaded 13 cutouts" in log and "SDSSJ0946+1006" in log
    fetch_logs = list((workdir / "logs" / "fetch_data").rglob("*.log"))
    assert len(fetch_logs) == 21  # one job per registered file
    assert all("copying from mirror" in log.read_text() for log in fetch_logs)
    # Up to date afterwards, even with the mirror moved: data are known by checksum.
    proc = snakemake(
        workdir,
        "-n",
        *gallery_only,
        "--config",
        "run_name=pytest_run",
        mirror=workdir / "elsewhere",
    )
    assert "Nothing to be done" in proc.stdout + proc.stderr, proc.stdout + proc.stderr


def test_log_stretch_handles_nonpositive_pixels():
    image = np.linspace(-1.0, 10.0, 10_000).reshape(100, 100)
    vmin, vmax = log_stretch_limits(image)
    assert vmax == 10.0 and vmin == pytest.approx(10.0 / 1000)
    vmin, vmax = log_stretch_limits(np.zeros((4, 4)))
    assert 0 < vmin < vmax


def _job_stats(output: str) -> dict[str, int]:
    """The 'Job stats' table of a Snakemake run/dry run as {rule: count}."""
    lines = output.split("Job stats:")[-1].splitlines()
    stats = {}
    for line in lines[3:]:
        parts = line.split()
        if len(parts) != 2 or not parts[1].isdigit():
            break
        if parts[0] != "total":
            stats[parts[0]] = int(parts[1])
    return stats


def _sim_only(workdir: Path) -> str:
    return _stages(
        workdir,
        False,
        True,
        train=False,
        evaluate=False,
        calibrate=False,
        cdm_grid=False,
        hst=False,
        figures=False,
        summary=False,
    )


def test_dry_run_simulation_jobs_per_scene(workdir, data_dir):
    proc = snakemake(workdir, "-n", "--configfile", _sim_only(workdir), mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    stats = _job_stats(proc.stdout)
    from subslope import config as cfgmod

    sim = cfgmod.load(workdir / "config" / "config.yaml", env=False)["simulation"]
    n_mult = len(sim["multipliers"])
    # one job per shard of the EPL scenes; per shard and multiplier of the CDM scenes
    # (the scene's own multipliers where it lists them)
    cdm = {s for s in sim["scenes"] if s in ("nfw", "tnfw") or "nfw_ref" in s}
    epl = set(sim["scenes"]) - cdm
    assert stats["simulate_shard"] == sum(sim["scenes"][s]["n_shards"] for s in epl)
    assert stats["simulate_cdm_shard"] == sum(
        len(sim["scenes"][s].get("multipliers") or sim["multipliers"])
        * sim["scenes"][s]["n_shards"]
        for s in cdm
    )
    assert n_mult == 5
    assert stats["compute_whitening"] == 1 and stats["plot_scene_examples"] == len(sim["scenes"])
    assert "train_estimator" not in stats and "evaluate_profiles" not in stats
    last_train = sim["scenes"]["train"]["n_shards"] - 1
    for path in (
        "train/shard_0.h5",
        f"train/shard_{last_train}.h5",
        "validation/shard_0.h5",
        "test_epl/shard_1.h5",
        "nfw/a0.5/shard_0.h5",
        "nfw/a1/shard_0.h5",
        "nfw/a4/shard_0.h5",
        "tnfw/a4/shard_0.h5",
    ):
        assert f"results/simulate_shard/{path}" in proc.stdout, path


#: Rules of each stage after simulate.
STAGE_RULES = {
    "train": {"train_estimator"},
    "evaluate": {"evaluate_profiles", "evaluate_cdm_profiles"},
    "calibrate": {"calibrate_threshold", "summarize_coverage"},
    "cdm_grid": {"effective_slope", "measure_cdm_grid", "measure_epl_control", "measure_abundance"},
    "null_tests": {
        "null_tests",
        "halo_free_profiles",
        "halo_free_null",
        "subhalo_free_profiles",
        "cdm_visibility",
    },
    "hst": {"analyze_hst"},
    "figures": {"plot_training_curves", "plot_validation"},
    "signal_budget": {
        "signal_budget",
        "signal_budget_cdm",
        "summarize_signal_budget",
        "concentration_contrast",
    },
    "summary": {"write_summary"},
}


def test_dry_run_tiny_job_counts(workdir, data_dir):
    proc = snakemake(workdir, "-n", "--configfile", "config/tiny.yaml", mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    stats = _job_stats(proc.stdout)
    expected = {
        "simulate_shard": 10,  # train 2, validation, test_epl, 2 null, 4 matched controls
        "simulate_cdm_shard": 4,  # nfw, tnfw, nfw_ref, tnfw_ref at a = 1
        "compute_whitening": 1,
        "plot_scene_examples": 13,
        "fit_lens_light": 1,
        "check_domain": 1,
        "train_estimator": 1,
        "plot_training_curves": 1,
        "evaluate_profiles": 8,
        "evaluate_cdm_profiles": 4,
        "calibrate_threshold": 2,
        "summarize_coverage": 1,
        "effective_slope": 1,
        "measure_epl_control": 1,
        "measure_abundance": 1,
        "measure_cdm_grid": 1,
        "null_tests": 1,
        "halo_free_profiles": 1,
        "halo_free_null": 1,
        "subhalo_free_profiles": 4,
        "cdm_visibility": 1,
        "analyze_hst": 1,
        "plot_validation": 1,
        "signal_budget": 8,  # shard 0 of train, test_epl, the two null scenes, the controls
        "signal_budget_cdm": 4,  # shard 0 of every CDM scene at each multiplier
        "summarize_signal_budget": 1,
        "write_summary": 1,
        "all": 1,
    }
    # fetch_data and the gallery may already have run in this work folder
    assert {
        k: v for k, v in stats.items() if k not in ("fetch_data", "plot_hst_gallery")
    } == expected, stats


@pytest.mark.parametrize("off", ["train", "calibrate", "cdm_grid", "signal_budget"])
def test_dry_run_disabled_stage_runs_no_rule_of_it(workdir, data_dir, off):
    """A stage switched off runs none of its rules, nor do the stages that need it."""
    needs = {
        "train": {"evaluate", "calibrate", "cdm_grid", "null_tests", "hst", "figures", "summary"},
        "evaluate": {"calibrate", "cdm_grid", "null_tests", "hst"},
        "calibrate": {"null_tests", "hst"},
    }
    flags = workdir / "config" / f"tiny_no_{off}.yaml"
    flags.write_text(f"stages:\n  {off}: false\n")
    proc = snakemake(workdir, "-n", "--configfile", "config/tiny.yaml", str(flags), mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    stats = _job_stats(proc.stdout)
    dead = {off} | needs.get(off, set())
    for stage, rules in STAGE_RULES.items():
        if stage in dead:
            assert not rules & set(stats), (stage, stats)
        elif stage != "figures" or "calibrate" not in dead:
            assert rules & set(stats), (stage, stats)
    if off == "cdm_grid":
        assert stats["analyze_hst"] == 1 and "measure_cdm_grid" not in stats
        assert not {"subhalo_free_profiles", "cdm_visibility"} & set(stats)  # no CDM grid
    if off == "calibrate":  # figures still plot the training curves and write the summary
        assert stats["write_summary"] == 1 and "plot_validation" not in stats


# ---------------------------------------------------------------------------------------
# the real tiny campaign, run once (in a folder of its own: tests/conftest.py)


@pytest.fixture
def campaign(tiny_run) -> Path:
    """The folder of the finished tiny campaign."""
    return tiny_run.parent


#: The CSVs beside results/summary.md.
SUMMARY_TABLES = SUMMARY_CSVS

FIGURES = (
    "hst_gallery",
    "training_curves",
    "coverage",
    "fig2_validation",
    "fig3_stacks",
    "fig4_concentration_grid",
    "fig5_hst_profiles",
    "fig6_hst_combined",
    "null_tests",
    "signal_budget",
    "response",
)


@pytest.mark.slow
def test_real_run_tiny_simulation(tiny_run, campaign):
    from subslope.io import shards
    from subslope.simulation import rerender

    results = tiny_run
    paths = sorted((results / "simulate_shard").rglob("*.h5"))
    rel = sorted(str(p.relative_to(results / "simulate_shard")) for p in paths)
    assert rel == [
        "epl_control_15/shard_0.h5",
        "epl_control_24/shard_0.h5",
        "epl_control_ref_15/shard_0.h5",
        "epl_control_ref_24/shard_0.h5",
        "nfw/a1/shard_0.h5",
        "nfw_ref/a1/shard_0.h5",
        "null_nosub/shard_0.h5",
        "null_nosub_los/shard_0.h5",
        "test_epl/shard_0.h5",
        "tnfw/a1/shard_0.h5",
        "tnfw_ref/a1/shard_0.h5",
        "train/shard_0.h5",
        "train/shard_1.h5",
        "validation/shard_0.h5",
    ]
    for p in paths:
        with shards.open_shard(p) as s:
            assert len(s) in (3, 4, 8) and np.all(np.isfinite(s.images[()]))
    # the workflow's shard equals the package's (same config, same seed streams)
    with shards.open_shard(results / "simulate_shard" / "train" / "shard_1.h5") as s:
        np.testing.assert_array_equal(
            rerender.rerender(
                s.path,
                2,
                cosmos=[campaign / "resources" / f for f in ("cosmos", "cosmos_extension")],
            ),
            s.images[2],
        )
    white = json.loads((results / "compute_whitening" / "whitening.json").read_text())
    assert white["n_images"] == 6 and white["std"] > 0 and len(white["shards"]) == 2
    for scene in ("train", "validation", "test_epl", "nfw", "tnfw"):
        png = results / "figures" / f"scene_examples_{scene}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", scene
    assert "plotted images" in (campaign / "logs" / "plot_scene_examples" / "train.log").read_text()
    assert (
        "per image" in (campaign / "logs" / "simulate_shard" / "train" / "shard_0.log").read_text()
    )


@pytest.mark.slow
def test_tiny_campaign_logs_hold_no_torch_guard_notices(tiny_run, campaign):
    """torch's per-guard notice of the traced-graph cache (hundreds per job) reaches
    neither a job's log nor the terminal of the run."""
    from subslope.render.kernels import PRECOMPILE_GUARD_NOTICE

    notice = PRECOMPILE_GUARD_NOTICE.split("%s")[-1].strip()
    shard_log = campaign / "logs" / "simulate_shard" / "train" / "shard_0.log"
    assert shard_log.read_text().strip(), "the shard job wrote no log"
    noisy = [str(p) for p in (campaign / "logs").rglob("*.log") if notice in p.read_text()]
    assert not noisy, noisy
    terminal = json.loads((campaign.parent / "tiny_campaign.json").read_text())["output"]
    assert notice not in terminal


@pytest.mark.slow
def test_results_page_of_the_tiny_campaign(tiny_run, campaign, tmp_path):
    from subslope.campaigns.results_page import write_results_page

    record = json.loads((tiny_run / "run.json").read_text())
    assert record["run_name"] == "tiny" and record["machine"]["cores"] >= 1
    page = write_results_page(tiny_run, tmp_path / "results.md").read_text()
    assert "--configfile config/tiny.yaml" in page and "## Verdict" in page
    assert "### HST measurement" in page and "not recorded" not in page


@pytest.mark.slow
def test_tiny_campaign_signal_budget_and_leave_one_out(tiny_run):
    import pandas as pd

    rows = pd.concat(pd.read_csv(p) for p in (tiny_run / "signal_budget").rglob("shard_0.csv"))
    controls = {"epl_control_15", "epl_control_24", "epl_control_ref_15", "epl_control_ref_24"}
    cdm = {"nfw", "tnfw", "nfw_ref", "tnfw_ref"}
    assert (
        set(rows["scene"]) == {"train", "test_epl", "null_nosub", "null_nosub_los"} | cdm | controls
    )
    assert np.isfinite(rows[["dchi2_fixed", "dchi2_linear", "dchi2_refit"]]).all().all()
    assert (rows["dchi2_linear"] <= rows["dchi2_fixed"] * (1 + 1e-9)).all()
    assert (rows["dchi2_refit"] <= rows["dchi2_fixed"] * (1 + 1e-9)).all()
    assert (rows["dchi2_refit"] >= 0).all()
    nulls = rows[rows["scene"].str.startswith("null")]
    assert (nulls["dchi2_fixed"] == 0).all()
    table = pd.read_csv(tiny_run / "signal_budget" / "signal_budget.csv")
    assert len(table) == 12 and (tiny_run / "figures" / "signal_budget.png").stat().st_size > 0
    loo = pd.read_csv(tiny_run / "analyze_hst" / "leave_one_out.csv")
    assert len(loo) == 2 and set(loo["n_images"]) == {1}
    summary = (tiny_run / "summary.md").read_text()
    assert "## Signal budget" in summary and "left out" in summary


@pytest.mark.slow
def test_hst_profiles_are_the_ones_the_workflow_wrote(tiny_run, campaign):
    import h5py

    from subslope import config as cfgmod
    from subslope.stages.hst import hst_profiles

    config = cfgmod.load(campaign / "config" / "tiny.yaml", env=False)
    config["data"]["resources_dir"] = str(campaign / config["data"]["resources_dir"])
    with h5py.File(tiny_run / "analyze_hst" / "profiles.h5") as fh:
        written, gammas = fh["log_ratio"][()], fh["gammas"][()]
        names = [n.decode() for n in fh["names"][()]]
        centres = fh["lens_x"][()], fh["lens_y"][()]
    got, geometry, prof, meta = hst_profiles(
        tiny_run / "train_estimator" / "model.pt",
        Path(config["data"]["resources_dir"]) / "hst",
        gammas,
        lens_centre=config["hst"]["lens_centre"],
        pixel_scale=config["instrument"]["pixel_scale"],
        device="cpu",
        config=config,
    )
    assert got == names and meta["whitening"]["std"] > 0
    np.testing.assert_array_equal(geometry["lens_x"], centres[0])
    np.testing.assert_array_equal(geometry["lens_y"], centres[1])
    assert prof.shape == written.shape == (13, gammas.size)
    np.testing.assert_allclose(prof, written, rtol=0, atol=1e-4)


@pytest.mark.slow
def test_real_run_tiny_campaign_outputs(tiny_run, campaign):
    import h5py
    import pandas as pd

    from subslope.nre import load_estimator
    from subslope.stages.summary import SUMMARY_SECTIONS

    results = tiny_run
    for stem in FIGURES:
        png, pdf = results / "figures" / f"{stem}.png", results / "figures" / f"{stem}.pdf"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", stem
        assert pdf.read_bytes()[:5] == b"%PDF-", stem
        if stem != "hst_gallery":
            assert b"run_name=tiny" in pdf.read_bytes() and b"run_name=tiny" in png.read_bytes(), (
                stem
            )
    model, meta = load_estimator(results / "train_estimator" / "model.pt")
    assert meta["whitening"]["std"] > 0
    assert len(pd.read_csv(results / "train_estimator" / "training_log.csv")) >= 1
    ckpts = list((results / "checkpoints" / "train_estimator").rglob("last.pt"))
    assert len(ckpts) == 1  # kept: not a declared output
    with h5py.File(results / "evaluate_profiles" / "test_epl" / "shard_0.h5") as fh:
        assert fh["log_ratio"].shape == (8, 19) and np.all(np.isfinite(fh["gamma_true"][()]))
    with h5py.File(results / "evaluate_profiles" / "nfw" / "a1" / "shard_0.h5") as fh:
        assert np.all(fh["c_multiplier"][()] == 1.0) and np.all(np.isnan(fh["gamma_true"][()]))
    for n in (1, 2):
        assert (results / "calibrate_threshold" / f"N{n}.npz").is_file()
    thr = json.loads((results / "summarize_coverage" / "thresholds.json").read_text())
    assert set(thr["tau"]) == {"1", "2"}
    cal = pd.read_csv(results / "summarize_coverage" / "calibration.csv")
    assert cal["n_images"].tolist() == [1, 2]
    grid = pd.read_csv(results / "measure_cdm_grid" / "cdm_grid.csv")
    cdm = {"nfw", "tnfw", "nfw_ref", "tnfw_ref"}  # both grids
    assert set(grid["scene"]) == cdm and set(grid["multiplier"]) == {1.0}
    slopes = pd.read_csv(results / "measure_cdm_grid" / "effective_slope.csv")
    assert len(slopes) == 8 and set(slopes["scene"]) == cdm  # 2 sets per scene
    assert np.all((slopes["gamma_eff"] > 1.0) & (slopes["gamma_eff"] < 3.0))
    for scene, group in slopes.groupby("scene"):
        row = grid[grid["scene"] == scene].iloc[0]
        assert row["reference"] == pytest.approx(group["gamma_eff"].median())
        assert row["distance"] == pytest.approx(row["median"] - row["reference"])
    hst = pd.read_csv(results / "analyze_hst" / "intervals.csv")
    assert len(hst) == 14 and hst["system"].iloc[-1] == "combined" and hst["n_images"].iloc[-1] == 2
    assert np.all(np.abs(hst["lens_x"].iloc[:13]) < 0.4) and np.all(
        np.abs(hst["lens_y"].iloc[:13]) < 0.4
    )
    summary = (results / "summary.md").read_text()
    for section in SUMMARY_SECTIONS:
        assert f"## {section}" in summary, section
    assert "`tiny`" in summary and "config/tiny.yaml" in summary
    for name in SUMMARY_TABLES:
        assert (results / f"{name}.csv").is_file(), name
    runtime = pd.read_csv(results / "stage_runtime.csv").set_index("stage")
    # 9 shards of the field grid's campaign, 2 of the reference grid, 4 matched controls
    assert runtime.loc["simulate", "jobs"] == 15 and runtime.loc["train", "seconds"] > 0
    # validation, test_epl, 4 CDM, 4 controls, 2 null scenes
    assert runtime.loc["evaluate", "jobs"] == 12
    # null_tests, halo_free_profiles, halo_free_null, 4 subhalo_free_profiles, cdm_visibility
    assert runtime.loc["null_tests", "jobs"] == 8
    null = pd.read_csv(results / "null_tests" / "null_tests.csv")
    assert null["scene"].tolist() == ["null_nosub", "null_nosub_los"]
    assert (null["n_stacks"] == 2).all() and (null["n_per_stack"] == 2).all()
    free = pd.read_csv(results / "null_tests" / "halo_free.csv")
    assert free["variant"].tolist() == ["original", "sheets_kept", "sheets_removed"]
    assert (free["n_images"] == 8).all() and (free["n_stacks"] == 4).all()
    assert free["passes"].iloc[1:].isin([True, False]).all()
    bias = pd.read_csv(results / "null_tests" / "nsub_bias.csv")
    assert bias["n_images"].sum() == 8
    assert "Rule `halo_free_null` not run" not in summary
    seen = pd.read_csv(results / "null_tests" / "cdm_visibility.csv")
    assert seen["scene"].tolist() == ["nfw", "nfw_ref", "tnfw", "tnfw_ref"]
    assert (seen["n_sets"] == 2).all()
    assert seen["visible"].isin([True, False]).all() and "Rule `cdm_visibility`" not in summary
    assert (campaign / "logs" / "train_estimator.log").read_text().count("training done") == 1


@pytest.mark.slow
def test_real_run_tiny_second_run_does_nothing(tiny_run, campaign, data_dir):
    proc = snakemake(campaign, "-n", *TINY, mirror=data_dir)
    assert "Nothing to be done" in proc.stdout + proc.stderr, proc.stdout + proc.stderr


@pytest.mark.slow
def test_real_run_tiny_reruns(tiny_run, campaign, data_dir):
    # -R calibrate_threshold: calibration and what depends on it, nothing upstream
    proc = snakemake(campaign, "-n", *TINY, "-R", "calibrate_threshold", mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    assert _job_stats(proc.stdout) == {
        "calibrate_threshold": 2,
        "summarize_coverage": 1,
        "null_tests": 1,
        "analyze_hst": 1,
        "plot_validation": 1,
        "write_summary": 1,
        "all": 1,
    }
    # appending a multiplier simulates and evaluates only the new one
    more = campaign / "config" / "tiny_more.yaml"
    more.write_text(
        (campaign / "config" / "tiny.yaml")
        .read_text()
        .replace("multipliers: [1.0]", "multipliers: [1.0, 2.0]")
    )
    proc = snakemake(campaign, "-n", "--configfile", str(more), mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    assert _job_stats(proc.stdout) == {
        "simulate_cdm_shard": 4,  # both grids' NFW and tNFW scenes
        "evaluate_cdm_profiles": 4,
        "effective_slope": 1,  # one cheap job over every CDM shard
        "measure_cdm_grid": 1,
        "subhalo_free_profiles": 4,  # the new multiplier's sets without their subhalos
        "cdm_visibility": 1,
        "signal_budget_cdm": 4,
        "summarize_signal_budget": 1,
        "analyze_hst": 1,
        "write_summary": 1,
        "all": 1,
    }
    assert "results/simulate_shard/nfw/a2/shard_0.h5" in proc.stdout


def test_readme_python_example_runs_on_the_tiny_campaign(tiny_run, campaign, capsys):
    """The README's Python block, as written but for the config file (the tiny
    campaign's), run in the finished tiny campaign's folder: one line per image with a
    γ_MLE on the grid and an interval around it."""
    readme = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    block = readme.split("### From Python", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert 'config.load("config/config.yaml")' in block
    code = block.replace('config.load("config/config.yaml")', 'config.load("config/tiny.yaml")')
    here = os.getcwd()
    try:
        os.chdir(campaign)
        exec(compile(code, "README.md", "exec"), {"__name__": "readme_example"})
    finally:
        os.chdir(here)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("γ ")]
    assert len(lines) == 4
    for line in lines:
        mle, lo, hi = (float(v) for v in re.findall(r"\d+\.\d+", line)[1:4])
        assert 1.1 <= lo <= mle <= hi <= 2.9
