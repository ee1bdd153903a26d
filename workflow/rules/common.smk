# Shared set-up: configuration validation and helpers used by every stage.

import os

from snakemake.utils import validate

import subslope.config
import subslope.resources


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


def all_targets():
    """Final outputs of the stages switched on in config['stages']."""
    targets = rules.fetch_data.output
    if config["stages"]["gallery"]:
        targets = targets + rules.plot_hst_gallery.output
    return targets
