# subslope: subhalo effective density slope from HST strong lenses with neural
# likelihood-ratio estimation (Zhang, Sengul & Dvorkin 2023).
# This file is the table of contents of the workflow. Each stage has one flag
# config["stages"][<stage>], one rule file workflow/rules/<stage>.smk and one package
# module subslope.stages.<stage> that its thin workflow/scripts call:
#
#   data      fetch_data (always on)            gallery   plot_hst_gallery
#   simulate  shards, whitening, scene figures  domain    HST lens-light fits, domain check
#   train     train_estimator                   evaluate  profiles on the gamma grid
#   calibrate thresholds per N, coverage        cdm_grid  concentration grid (figure 4)
#   hst       the 13 real lenses (figures 5, 6) figures   training curves, figures 2, 3
#   null_tests scenes without subhalos          summary   results/summary.md
#   signal_budget the ideal observer's Delta chi^2 of every scene's subhalos
#
# Every output is flagged update(): Snakemake leaves the previous version in place while
# its job runs (a copy waits in .snakemake/backups/) and puts it back if the job fails,
# so a rerun that fails on a bad input never costs the good results of the last run. The
# jobs write through subslope.io.atomic, so an output is either the old or the new file.
#
# Run:  snakemake --cores 2                        (config/config.yaml)
#       snakemake --cores 2 --configfile my.yaml   (another campaign)

from snakemake.exceptions import WorkflowError
from snakemake.utils import min_version

min_version("9.0")


# The campaign config: the --configfile file(s), or config/config.yaml when none is given,
# each read with the files it names under `base:`, then --config key=value on top. The
# CLI (`subslope ... --config F`) reads a file the same way (subslope.config.load), so
# one file name is one campaign (docs/configuration.md).
import subslope.config

_CONFIG_FILES = [str(f) for f in workflow.overwrite_configfiles] or [
    "config/config.yaml"
]
try:
    _RAW = subslope.config.read_files(_CONFIG_FILES)
except subslope.config.ConfigError as exc:
    raise WorkflowError(str(exc)) from None
# Snakemake's command-line config holds the --configfile keys and --config on top.
_COMMAND_LINE = dict(workflow.config_settings.overwrite_config or {})
_COMMAND_LINE.pop(subslope.config.BASE_KEY, None)
config.clear()
config.update(subslope.config.deep_merge(_RAW, _COMMAND_LINE))


# Wildcards of every rule. Scene names: letters, digits, '_' (no '/', so the CDM pattern
# <scene>/a<a>/ never clashes); shards and stack sizes: integers; multipliers: numbers
# as multiplier_label writes them (1, 0.5, 1e-05).
wildcard_constraints:
    scene=r"[A-Za-z][A-Za-z0-9_]*",
    shard=r"[0-9]+",
    n=r"[0-9]+",
    multiplier=r"[0-9]+(\.[0-9]+)?(e[-+]?[0-9]+)?",


# `serial` (a unit per grouped shard or profile job) is counted within one cluster job
# only: profiles/slurm allows one at a time, so a group's members run one after another
# and the group asks for the sum of their wall times (profiles/slurm/config.yaml).
resource_scopes:
    serial="local",


include: "workflow/rules/common.smk"
include: "workflow/rules/data.smk"
include: "workflow/rules/gallery.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/domain.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/cdm_grid.smk"
include: "workflow/rules/null_tests.smk"
include: "workflow/rules/signal_budget.smk"
include: "workflow/rules/hst.smk"
include: "workflow/rules/figures.smk"
include: "workflow/rules/summary.smk"


rule all:
    default_target: True
    input:
        all_targets(),
