"""The Snakemake workflow: lint, dry run, config errors, and a real run of fetch + gallery.

Every run happens in a private copy of the workflow under a temporary folder (so tests
never touch the repository's results/ or lock it), with the data mirror passed through
the SUBSLOPE_DATA_MIRROR environment variable.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from subslope.plotting import log_stretch_limits

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """A copy of Snakefile, workflow/ and config/ (the schema symlink dereferenced)."""
    if not SNAKEMAKE.exists():
        pytest.skip(f"snakemake not found next to {sys.executable}")
    root = tmp_path_factory.mktemp("workflow")
    shutil.copy(REPO / "Snakefile", root)
    shutil.copytree(REPO / "workflow", root / "workflow", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copytree(REPO / "config", root / "config")
    return root


def snakemake(workdir: Path, *args: str, mirror: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if mirror is not None:
        env["SUBSLOPE_DATA_MIRROR"] = str(mirror)
    return subprocess.run(
        [str(SNAKEMAKE), *args], cwd=workdir, env=env, capture_output=True, text=True, timeout=300
    )


def test_lint_clean(workdir):
    proc = snakemake(workdir, "--lint")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Lints for" not in proc.stdout + proc.stderr


def test_dry_run_lists_stages(workdir, data_dir):
    proc = snakemake(workdir, "-n", mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    for rule in ("fetch_data", "plot_hst_gallery", "all"):
        assert rule in proc.stdout
    off = workdir / "config" / "no_gallery.yaml"
    off.write_text("stages:\n  gallery: false\n")
    proc = snakemake(workdir, "-n", "--configfile", str(off), mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    assert "fetch_data" in proc.stdout and "plot_hst_gallery" not in proc.stdout


def test_bad_config_stops_before_any_job(workdir, data_dir):
    bad = workdir / "config" / "bad.yaml"
    bad.write_text("instrument:\n  pixel_scale: 5.0\ndata:\n  mirorr: /x\n")
    proc = snakemake(workdir, "--cores", "1", "--configfile", str(bad), mirror=data_dir)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "instrument.pixel_scale" in out and "(0, 1.0]" in out
    assert "data.mirorr" in out
    assert not (workdir / "resources").exists() and not (workdir / "results").exists()


def _stages(workdir: Path, gallery: bool, simulation: bool) -> str:
    path = workdir / "config" / f"stages_{int(gallery)}{int(simulation)}.yaml"
    path.write_text(f"stages:\n  gallery: {str(gallery).lower()}\n  simulation: {str(simulation).lower()}\n")
    return str(path)


@pytest.mark.slow
def test_real_run_fetch_and_gallery(workdir, data_dir):
    gallery_only = ("--configfile", _stages(workdir, True, False))
    proc = snakemake(workdir, "--cores", "2", *gallery_only, "--config", "run_name=pytest_run", mirror=data_dir)
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
    assert (workdir / "logs" / "fetch_data.log").read_text().count("copying from mirror") == 18
    # Up to date afterwards, even with the mirror moved: data are known by checksum.
    proc = snakemake(workdir, "-n", *gallery_only, "--config", "run_name=pytest_run", mirror=workdir / "elsewhere")
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


def test_dry_run_simulation_jobs_per_scene(workdir, data_dir):
    proc = snakemake(workdir, "-n", "--configfile", _stages(workdir, False, True), mirror=data_dir)
    assert proc.returncode == 0, proc.stderr
    stats = _job_stats(proc.stdout)
    # reduced config: train 2 shards, validation 1, test_epl 1; nfw, tnfw 1 shard x 2 multipliers
    assert stats["simulate_shard"] == 4 and stats["simulate_cdm_shard"] == 4, stats
    assert stats["compute_whitening"] == 1 and stats["plot_scene_examples"] == 5, stats
    for path in ("train/shard_0.h5", "train/shard_1.h5", "validation/shard_0.h5", "test_epl/shard_0.h5",
                 "nfw/a1/shard_0.h5", "nfw/a4/shard_0.h5", "tnfw/a1/shard_0.h5", "tnfw/a4/shard_0.h5"):
        assert f"results/simulate_shard/{path}" in proc.stdout, path
    proc = snakemake(workdir, "-n", "--configfile", _stages(workdir, False, False), mirror=data_dir)
    assert proc.returncode == 0 and "simulate_shard" not in proc.stdout


@pytest.mark.slow
def test_real_run_tiny_simulation(workdir, data_dir):
    from subslope import shards, simulate

    tiny = ["--configfile", "config/tiny.yaml"]
    proc = snakemake(workdir, "--cores", "2", *tiny, mirror=data_dir)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    results = workdir / "results"
    paths = sorted((results / "simulate_shard").rglob("*.h5"))
    rel = sorted(str(p.relative_to(results / "simulate_shard")) for p in paths)
    assert rel == ["nfw/a1/shard_0.h5", "test_epl/shard_0.h5", "tnfw/a1/shard_0.h5", "train/shard_0.h5",
                   "train/shard_1.h5", "validation/shard_0.h5"]
    for p in paths:
        with shards.open_shard(p) as s:
            assert len(s) in (2, 3) and np.all(np.isfinite(s.images[()]))
    # the workflow's shard equals the package's (same config, same seed streams)
    with shards.open_shard(results / "simulate_shard" / "train" / "shard_1.h5") as s:
        np.testing.assert_array_equal(simulate.rerender(s.path, 2, cosmos=workdir / "resources" / "cosmos"),
                                      s.images[2])
    white = json.loads((results / "compute_whitening" / "whitening.json").read_text())
    assert white["n_images"] == 6 and white["std"] > 0 and len(white["shards"]) == 2
    for scene in ("train", "validation", "test_epl", "nfw", "tnfw"):
        png = results / "figures" / f"scene_examples_{scene}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", scene
    assert "plotted images" in (workdir / "logs" / "plot_scene_examples" / "train.log").read_text()
    assert "per image" in (workdir / "logs" / "simulate_shard" / "train" / "shard_0.log").read_text()

    proc = snakemake(workdir, "-n", *tiny, mirror=data_dir)
    assert "Nothing to be done" in proc.stdout + proc.stderr, proc.stdout + proc.stderr

    before = {p: p.stat().st_mtime_ns for p in paths}
    proc = snakemake(workdir, "--cores", "1", *tiny, "-R", "compute_whitening", mirror=data_dir)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert set(_job_stats(proc.stdout + proc.stderr)) <= {"compute_whitening", "all"}
    assert _job_stats(proc.stdout + proc.stderr)["compute_whitening"] == 1
    assert {p: p.stat().st_mtime_ns for p in paths} == before
