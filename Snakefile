# subslope: subhalo effective density slope from HST strong lenses with neural
# likelihood-ratio estimation (Zhang, Sengul & Dvorkin 2023).
# This file is the table of contents of the workflow; each stage lives in its own
# workflow/rules/<stage>.smk and the logic in the `subslope` package (src/subslope).
#
# Stages (each switched by config["stages"]): fetch data -> simulate shards -> whitening
# -> train the estimator -> profiles on the gamma grid -> thresholds per stack size and
# their coverage -> CDM concentration grid -> real HST lenses -> figures + summary.
#
# Run:  snakemake --cores 2                        (config/config.yaml)
#       snakemake --cores 2 --configfile my.yaml   (another campaign)

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/resources.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/inference.smk"
include: "workflow/rules/figures.smk"


rule all:
    default_target: True
    input:
        all_targets(),
