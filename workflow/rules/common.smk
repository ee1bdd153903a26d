# Shared set-up: configuration validation, and the helpers every stage uses by name
# (subslope.campaigns.targets).

import glob
import os
import re

from snakemake.logging import logger
from snakemake.exceptions import WorkflowError

import subslope.devices
import subslope.logs
import subslope.io.atomic
import subslope.plan
import subslope.config
import subslope.io.resources
import subslope.io.observation_set
import subslope.simulation.resolve
import subslope.stages.train
import subslope.campaigns.targets

# Validate once, when the workflow loads: the schema (types, ranges, defaults filled
# in) and every cross-key check, with messages that name the key and what is allowed.
# workflow/schemas/config.schema.yaml links to the same schema for `snakemake --lint`.
try:
    config.update(subslope.config.validate(config))
except subslope.config.ConfigError as exc:
    raise WorkflowError(str(exc)) from None
subslope.config.apply_env_overrides(config)  # SUBSLOPE_DATA_MIRROR -> data.mirror
# What only the scenes, the data registry and the HST catalogue show, before any job.
_PROBLEMS = subslope.plan.plan_problems(config)
if _PROBLEMS:
    raise WorkflowError("invalid configuration:\n  - " + "\n  - ".join(_PROBLEMS))
if workflow.is_main_process:
    for _warning in subslope.plan.plan_warnings(config):
        logger.warning(f"warning: {_warning}")
# Outputs of jobs that started and did not finish (killed, or failed and restored by
# update()) are made older than any input, so that their jobs run again
# (subslope.logs). Only the main process: a cluster job's own Snakemake leaves the
# records of the jobs running beside it alone.
if workflow.is_main_process:
    # A data file deleted after it was fetched is put back here, not by fetch_data, so
    # that none of its readers runs again (subslope.io.resources.restore_deleted); a
    # fetch of it that failed meanwhile is done with.
    _RESTORED = subslope.io.resources.restore_deleted(
        config["data"]["resources_dir"], mirror=config["data"]["mirror"]
    )
    for _data in _RESTORED:
        logger.info(f"{_data} was deleted; restored from the data mirror")
    subslope.logs.forget_jobs_of(_RESTORED)
    for _stale in subslope.logs.mark_unfinished_outputs():
        logger.warning(f"{_stale}: its last job did not finish; that job runs again")
    for _tmp in subslope.io.atomic.remove_stale_temporaries_under("results"):
        logger.info(f"removed {_tmp}, left by a killed job")


# Before the first job, once the executor is known: a device this machine cannot serve
# (training.device: cuda without CUDA) on a local run, where the jobs run here; GPU
# requests on a SLURM cluster without GPUs. A cluster job checks its own node's device
# when it starts (subslope.devices.pick_device).
onstart:
    problems = []
    if workflow.remote_exec:
        pass
    elif workflow.executor_plugin.name == "slurm":
        problems = subslope.plan.slurm_gpu_problems(config)
    elif workflow.local_exec:
        problems = subslope.devices.device_problems(
            config, subslope.config.active_stages(config)
        )
    if problems:
        raise WorkflowError(
            "invalid configuration:\n  - " + "\n  - ".join(problems)
        )


# The campaign's files, computed once (subslope.campaigns.targets): the helpers and the
# plan the rule files use by name.
TARGETS = subslope.campaigns.targets.Targets(config)
for _name in subslope.campaigns.targets.HELPERS:
    globals()[_name] = getattr(TARGETS, _name)
for _name in subslope.campaigns.targets.CONSTANTS:
    globals()[_name] = getattr(TARGETS, _name)
for _name, _on in STAGE_ON.items():
    if config["stages"][_name] and not _on:
        logger.warning(
            f"stage {_name} is on but a stage it needs is off: it does not run"
        )
SUMMARY_CSVS = list(subslope.campaigns.targets.SUMMARY_CSVS)
CLASSIFIER_DIR = subslope.campaigns.targets.CLASSIFIER_DIR
SEEDS_CSV = subslope.campaigns.targets.SEEDS_CSV
CONFIG_FILES = [os.path.relpath(f) for f in _CONFIG_FILES]


def simulation_targets():
    return TARGETS.simulation_targets(rules, expand)


def benchmark_files():
    return TARGETS.benchmark_files()


def all_targets():
    return TARGETS.all_targets(rules, expand)


def summary_inputs(wildcards):
    return TARGETS.summary_inputs(rules)
