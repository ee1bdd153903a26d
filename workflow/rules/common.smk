# Shared set-up: configuration validation and helpers used by every stage.

import os

from snakemake.logging import logger
from snakemake.utils import validate

import subslope.campaign
import subslope.config
import subslope.resources
import subslope.shards
import subslope.simulate


# Validate once, when the workflow loads, against the schema shipped in the package
# (workflow/schemas/config.schema.yaml links to it). The first check gives a readable
# message naming the key and its allowed range; Snakemake's own validate() then fills
# the schema defaults into `config` in place (both use the same schema file).
subslope.config.validate(config)


validate(config, schema="../schemas/config.schema.yaml")
subslope.config.apply_env_overrides(config)  # SUBSLOPE_DATA_MIRROR -> data.mirror

RESOURCES = config["data"]["resources_dir"]
REGISTRY = subslope.resources.load_registry()


def resource_files(prefix):
    """Registered data files whose path starts with `prefix`, under RESOURCES."""
    return [
        f"{RESOURCES}/{entry.path}"
        for entry in REGISTRY
        if entry.path.startswith(prefix)
    ]


# Simulation: one entry {scene, shard, multiplier, path} per shard file of the config.
SHARD_JOBS = subslope.simulate.shard_jobs(config)
SIM_SCENES = sorted({job["scene"] for job in SHARD_JOBS})
# Scene names: letters, digits, '_' (no '/', so the CDM pattern <scene>/a<a>/ never clashes).
SCENE_WILDCARD = r"[A-Za-z][A-Za-z0-9_]*"


def simulation_hash(scene):
    """Hash of the config values that determine the images of `scene`'s shards.

    The list of multipliers is left out: a shard's seed depends on its multiplier's
    position in the list, so APPENDING a multiplier leaves the existing CDM shards (and
    their profiles) valid and only the new multiplier is simulated and evaluated.
    """
    if scene not in _SIM_HASH:  # cached: the config is validated again for every call
        sections = subslope.simulate.simulation_sections(config, scene)
        sections.pop("multipliers", None)
        _SIM_HASH[scene] = subslope.shards.config_hash(sections)
    return _SIM_HASH[scene]


_SIM_HASH = {}


def shard_files(scene):
    """All shard files of `scene` (every multiplier for CDM scenes)."""
    return [job["path"] for job in SHARD_JOBS if job["scene"] == scene]


def example_shard(scene):
    """The shard shown in the scene-example figure: shard 0 (a = 1 if simulated)."""
    jobs = [job for job in SHARD_JOBS if job["scene"] == scene and job["shard"] == 0]
    ones = [job for job in jobs if job["multiplier"] == 1.0]
    return (ones or jobs)[0]["path"]


def simulation_targets():
    """Shards, whitening statistics (if there are training shards) and scene figures."""
    targets = [job["path"] for job in SHARD_JOBS]
    if shard_files("train"):
        targets.append(rules.compute_whitening.output.json)
    targets += expand(rules.plot_scene_examples.output.png, scene=SIM_SCENES)
    return targets


# ---------------------------------------------------------------------------------------
# Stages. A stage runs when its flag and the flags of every stage it needs are on, so a
# switched-off stage never runs as a dependency of a later one.
STAGE_NEEDS = {
    "gallery": [],
    "simulation": [],
    "training": ["simulation"],
    "inference": ["training"],
    "calibration": ["inference"],
    "cdm_grid": ["inference"],
    "hst": ["calibration"],
    "figures": ["training"],
}


def _stage_on(name):
    return bool(config["stages"][name]) and all(_stage_on(need) for need in STAGE_NEEDS[name])


STAGE_ON = {name: _stage_on(name) for name in STAGE_NEEDS}
for _name, _on in STAGE_ON.items():
    if config["stages"][_name] and not _on:
        logger.warning(f"stage {_name} is on but a stage it needs is off: it does not run")


# ---------------------------------------------------------------------------------------
# Evaluation sets: which shards get profiles, and the calibration stack sizes.
CAL = config["calibration"]
CDM = config["cdm"]
RUN = config["run_name"]
CAL_N = sorted(CAL["n_images"])
GRID = config["inference"]["gamma_grid"]


def _check_scene(key, name, need_shards=True):
    if name not in {job["scene"] for job in SHARD_JOBS} and need_shards:
        raise ValueError(f"config key {key} = {name!r}: no shards of that scene (simulation.scenes.{name})")


if STAGE_ON["calibration"]:
    _check_scene("calibration.single_scene", CAL["single_scene"])
    _check_scene("calibration.stack_scene", CAL["stack_scene"])
    _per_set = subslope.simulate.resolved_scene(config, CAL["stack_scene"])[0].images_per_set
    if any(n > _per_set for n in CAL_N if n > 1):
        raise ValueError(f"config key calibration.n_images = {CAL_N}: N > 1 must not exceed the "
                         f"images_per_set = {_per_set} of calibration.stack_scene {CAL['stack_scene']!r}")
if STAGE_ON["cdm_grid"]:
    _check_scene("cdm.nfw_scene", CDM["nfw_scene"])
    if CDM["tnfw_scene"]:
        _check_scene("cdm.tnfw_scene", CDM["tnfw_scene"])
    _mults = {job["multiplier"] for job in SHARD_JOBS if job["scene"] == CDM["nfw_scene"]}
    if 1.0 not in _mults:
        raise ValueError("config key simulation.multipliers must include 1.0 (the CDM prediction, a = 1)")
if GRID["low"] >= GRID["high"]:
    raise ValueError(f"config keys inference.gamma_grid.low/high: need low < high, got {GRID}")


def eval_scenes():
    """Scenes whose shards are evaluated: the calibration scenes and the CDM scenes."""
    scenes = [CAL["single_scene"], CAL["stack_scene"], CDM["nfw_scene"], CDM["tnfw_scene"]]
    simulated = {job["scene"] for job in SHARD_JOBS}
    return [s for s in dict.fromkeys(scenes) if s in simulated]


def profile_path(job):
    """Profiles file of one shard job (mirrors the shard path)."""
    return job["path"].replace("results/simulate_shard/", "results/evaluate_profiles/", 1)


def profile_files(scene, multiplier=None):
    """Profiles files of every shard of `scene` (of one multiplier for CDM scenes)."""
    return [
        profile_path(job)
        for job in SHARD_JOBS
        if job["scene"] == scene and (multiplier is None or job["multiplier"] == multiplier)
    ]


def calibration_inputs(wildcards):
    """N = 1: single images of calibration.single_scene; N > 1: sets of stack_scene."""
    scene = CAL["single_scene"] if int(wildcards.n) == 1 else CAL["stack_scene"]
    return profile_files(scene)


def cdm_inputs():
    scenes = [CDM["nfw_scene"]] + ([CDM["tnfw_scene"]] if CDM["tnfw_scene"] else [])
    return [profile_path(job) for job in SHARD_JOBS if job["scene"] in scenes]


def derived_seed(section):
    """The section's seed, or one derived from the global seed when it is null."""
    value = config[section].get("seed")
    return subslope.campaign.derived_seed(config["seed"], section) if value is None else int(value)


def benchmark_files():
    """Benchmark TSVs of every job of the stages that run, grouped by stage."""
    out = {}
    if STAGE_ON["simulation"]:
        out["simulation"] = [
            job["path"].replace("results/simulate_shard/", "results/benchmarks/simulate_shard/").replace(".h5", ".tsv")
            for job in SHARD_JOBS
        ]
        if shard_files("train"):
            out["simulation"].append("results/benchmarks/compute_whitening.tsv")
    if STAGE_ON["training"]:
        out["training"] = ["results/benchmarks/train_estimator.tsv"]
    if STAGE_ON["inference"]:
        out["inference"] = [
            profile_path(job).replace("results/evaluate_profiles/", "results/benchmarks/evaluate_profiles/").replace(".h5", ".tsv")
            for job in SHARD_JOBS
            if job["scene"] in eval_scenes()
        ]
    if STAGE_ON["calibration"]:
        out["calibration"] = [f"results/benchmarks/calibrate_threshold/N{n}.tsv" for n in CAL_N]
        out["calibration"].append("results/benchmarks/summarize_coverage.tsv")
    if STAGE_ON["cdm_grid"]:
        out["cdm_grid"] = ["results/benchmarks/measure_cdm_grid.tsv"]
    if STAGE_ON["hst"]:
        out["hst"] = ["results/benchmarks/analyze_hst.tsv"]
    if STAGE_ON["figures"]:
        out["figures"] = ["results/benchmarks/plot_training_curves.tsv"]
        if STAGE_ON["calibration"]:
            out["figures"].append("results/benchmarks/plot_validation.tsv")
    return out


def all_targets():
    """Final outputs of the stages switched on in config['stages']."""
    targets = list(rules.fetch_data.output)
    if STAGE_ON["gallery"]:
        targets += rules.plot_hst_gallery.output
    if STAGE_ON["simulation"]:
        targets += simulation_targets()
    if STAGE_ON["training"]:
        targets += rules.train_estimator.output
    if STAGE_ON["inference"]:
        targets += [profile_path(job) for job in SHARD_JOBS if job["scene"] in eval_scenes()]
    if STAGE_ON["calibration"]:
        targets += rules.summarize_coverage.output
    if STAGE_ON["cdm_grid"]:
        targets += rules.measure_cdm_grid.output
    if STAGE_ON["hst"]:
        targets += rules.analyze_hst.output
    if STAGE_ON["figures"]:
        targets += rules.plot_training_curves.output
        if STAGE_ON["calibration"]:
            targets += rules.plot_validation.output
        targets += rules.write_summary.output
    return targets


# ---------------------------------------------------------------------------------------
# Summary: its inputs are the results of the stages that run (missing ones are reported
# as "not run"); its CSVs sit beside results/summary.md.
SUMMARY_CSVS = ["hst_result", "cdm_prediction", "coverage", "trend", "stage_runtime"]
# Hash of the whole validated config except the data location (machine-specific).
CONFIG_HASH = subslope.shards.config_hash({k: v for k, v in config.items() if k != "data"})[:16]
CONFIG_FILES = [os.path.relpath(f) for f in (workflow.overwrite_configfiles or workflow.configfiles)]


def summary_inputs(wildcards):
    inputs = {}
    if STAGE_ON["training"]:
        inputs["training_log"] = rules.train_estimator.output.log_csv
    if STAGE_ON["hst"]:
        inputs["hst"] = rules.analyze_hst.output.csv
    if STAGE_ON["cdm_grid"]:
        inputs["cdm"] = rules.measure_cdm_grid.output.csv
    if STAGE_ON["calibration"]:
        inputs["calibration"] = rules.summarize_coverage.output.csv
        inputs["trend"] = rules.plot_validation.output.trend
    return inputs
