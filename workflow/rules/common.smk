# Shared set-up: configuration validation and helpers used by every stage.

import os

from snakemake.utils import validate

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
    """Hash of the config values that determine the images of `scene`'s shards."""
    return subslope.shards.config_hash(subslope.simulate.simulation_sections(config, scene))


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


def all_targets():
    """Final outputs of the stages switched on in config['stages']."""
    targets = list(rules.fetch_data.output)
    if config["stages"]["gallery"]:
        targets += rules.plot_hst_gallery.output
    if config["stages"]["simulation"]:
        targets += simulation_targets()
    return targets
