"""config/paper.yaml (the paper-scale campaign) and the SLURM profile: the layered config
validates with the paper's numbers, and the dry-run DAG has the expected jobs per rule."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from subslope import config as cfgmod
from subslope.plan import count_cluster_jobs, host_rules

REPO = Path(__file__).resolve().parents[1]
SNAKEMAKE = Path(sys.executable).with_name("snakemake")


def _layered() -> dict:
    """paper.yaml on its base config.yaml, read as the workflow and the CLI read it."""
    return cfgmod.load(REPO / "config" / "paper.yaml", env=False)


def test_paper_config_has_the_paper_numbers():
    cfg = _layered()
    sim = cfg["simulation"]
    n_images = {s: v["n_shards"] * v["images_per_shard"] for s, v in sim["scenes"].items()}
    assert n_images["train"] == 5_000_000 and n_images["validation"] == 1_000
    for scene in ("test_epl", "nfw", "tnfw"):
        assert n_images[scene] == 100 * 13
    assert 1.0 in sim["multipliers"]
    assert sim["sources"]["cuts"] == {
        "mag_max": 20.0,
        "min_stamp_side": 64,
        "min_flux_radius": 10.0,
        "zphot_max": 1.0,
        "exclude": [],
    }
    assert (sim["sources"]["split"]["train"], sim["sources"]["split"]["test"]) == (0.96, 0.01)
    assert sim["sources"]["mag_renormalize"] is None
    assert cfg["training"]["arch"]["preset"] == "resnet50" and cfg["training"]["batch_size"] == 1000
    assert cfg["training"]["lr"] == 1e-3 and cfg["training"]["mask_factor"] == 1.5
    assert cfg["scenes"]["train"]["subhalos"]["count"] == {
        "dist": "uniform_int",
        "low": 0,
        "high": 3000,
    }
    assert cfg["scenes"]["validation"]["subhalos"]["count"]["high"] == 1800
    # the lens light that covers the HST lenses, in every scene
    assert all(s["lens_light"]["prior"] == "hst_joint" for s in cfg["scenes"].values())
    assert all(s["components"]["sky"] for s in cfg["scenes"].values())
    assert sim["sources"]["clean"]["enabled"] is True


@pytest.mark.slow
def test_paper_dag_through_the_slurm_profile(tmp_path, data_dir):
    if not SNAKEMAKE.exists():
        pytest.skip(f"snakemake not found next to {sys.executable}")
    pytest.importorskip("snakemake_executor_plugin_slurm", reason="pip install -e '.[slurm]'")
    for name in ("Snakefile",):
        shutil.copy(REPO / name, tmp_path)
    for folder in ("workflow", "config", "profiles"):
        shutil.copytree(
            REPO / folder, tmp_path / folder, ignore=shutil.ignore_patterns("__pycache__")
        )
    # the full COSMOS catalogue is placed by hand (config/paper.yaml); planning checks it is there
    (tmp_path / "resources" / "cosmos_23.5_full").mkdir(parents=True)
    env = dict(os.environ, SUBSLOPE_DATA_MIRROR=str(data_dir), OMP_NUM_THREADS="1")
    proc = subprocess.run(
        [str(SNAKEMAKE), "-n", "--profile", "profiles/slurm", "--configfile", "config/paper.yaml"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    lines = proc.stdout.split("Job stats:")[-1].splitlines()[3:]
    stats = {}
    for line in lines:
        parts = line.split()
        if len(parts) != 2 or not parts[1].isdigit():
            break
        stats[parts[0]] = int(parts[1])
    cfg = _layered()
    n_mult = len(cfg["simulation"]["multipliers"])
    n_null = sum(cfg["simulation"]["scenes"][s]["n_shards"] for s in cfg["null_tests"]["scenes"])
    assert n_null == 2  # the null scenes of config.yaml, one shard each
    cdm = cfg["cdm"]
    controls = [*cdm["field_controls"], *cdm["reference_controls"]]
    n_controls = sum(cfg["simulation"]["scenes"][s]["n_shards"] for s in controls)
    assert n_controls == 80  # 8 matched controls of 10 shards each
    assert stats["simulate_shard"] == 5000 + 1 + 10 + n_null + n_controls
    # both grids (nfw, tnfw, nfw_ref, tnfw_ref) at every multiplier, nfw_ref_centroid at
    # two, the 8 further scenes of the abundance series at a = 1
    n_cdm = len(cfgmod.cdm_grids(cfg)) * 2 * n_mult * 10 + 2 * 10 + 8 * 10
    assert stats["simulate_cdm_shard"] == stats["evaluate_cdm_profiles"] == n_cdm
    assert stats["evaluate_profiles"] == 1 + 10 + n_null + n_controls
    assert stats["calibrate_threshold"] == 6
    for rule in (
        "train_estimator",
        "compute_whitening",
        "measure_cdm_grid",
        "analyze_hst",
        "write_summary",
    ):
        assert stats[rule] == 1, rule
    # the cluster jobs: shard and profile jobs bundled by the profile's group-components
    jobs = count_cluster_jobs(proc.stdout, host_rules(tmp_path))
    size = _group_components()
    kinds = {
        "simulate": ("simulate_shard", "simulate_cdm_shard"),
        "evaluate": ("evaluate_profiles", "evaluate_cdm_profiles", "subhalo_free_profiles"),
    }
    for kind, rules in kinds.items():
        grouped = sum(n for key, n in jobs.items() if key.startswith(f"group {kind}:"))
        assert grouped == -(-sum(stats[r] for r in rules) // size[kind]), kind
        assert not any(r in jobs for r in rules)
    assert "fetch_data" not in jobs and "all" not in jobs  # on the submitting host
    assert sum(jobs.values()) <= 500, jobs


def _group_components() -> dict[str, int]:
    """The profile's ``group-components``, ``{group: jobs per cluster job}``."""
    import yaml

    profile = yaml.safe_load((REPO / "profiles" / "slurm" / "config.yaml").read_text())
    return {k: int(v) for k, v in (item.split("=") for item in profile["group-components"])}


def _group_jobs(dry_run: str) -> list[tuple[str, int]]:
    """(group, members) of every group job of a dry run: its header, then one indented
    record per member."""
    out: list[tuple[str, int]] = []
    for line in dry_run.splitlines():
        if "] Group job " in line:
            out.append((line.split("] Group job ")[1].split()[0], 0))
        elif out and line.startswith("    rule "):
            out[-1] = (out[-1][0], out[-1][1] + 1)
        elif line.startswith("rule ") or line.startswith("localrule "):
            out.append(("", 0))  # an ungrouped job ends the group's records
    return [g for g in out if g[0]]


def test_count_cluster_jobs_of_a_dry_run():
    text = "\n".join([
        "rule fetch_data:", "    output: a",
        "[Thu Dec  3 13:13:57 2026] Group job simulate (jobs in lexicogr. order):", "",
        "    [Thu Dec  3 13:13:57 2026]", "    rule simulate_shard:", "        output: s0",
        "    [Thu Dec  3 13:13:57 2026]", "    rule simulate_cdm_shard:", "        output: s1",
        "rule train_estimator:", "    output: m",
        "[Thu Dec  3 13:13:57 2026] Group job simulate (jobs in lexicogr. order):", "",
        "    [Thu Dec  3 13:13:57 2026]", "    rule simulate_shard:", "        output: s2",
        "rule all:", "    input: m",
    ])  # fmt: skip
    jobs = count_cluster_jobs(text, {"fetch_data", "all"})
    assert jobs == {
        "train_estimator": 1,
        "group simulate: simulate_cdm_shard, simulate_shard": 1,
        "group simulate: simulate_shard": 1,
    }
    assert host_rules(REPO) == {"all", "fetch_data"}


@pytest.mark.slow
def test_tiny_groups_through_the_slurm_profile(workdir, data_dir):
    pytest.importorskip("snakemake_executor_plugin_slurm", reason="pip install -e '.[slurm]'")
    env = dict(os.environ, SUBSLOPE_DATA_MIRROR=str(data_dir), OMP_NUM_THREADS="1")
    argv = ["-n", "--profile", "profiles/slurm", "--configfile", "config/tiny.yaml"]
    proc = subprocess.run([str(SNAKEMAKE), *argv], cwd=workdir, env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    # the 14 shard jobs of tiny.yaml (4 of them matched controls) in one cluster job; its
    # 12 profile jobs and 4 subhalo-free profile jobs in cluster jobs of at most 10
    # (group-components)
    assert sorted(_group_jobs(proc.stdout)) == [("evaluate", 6), ("evaluate", 10), ("simulate", 14)]
    assert _group_components() == {"simulate": 20, "evaluate": 10}
