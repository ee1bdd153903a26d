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
#   summary   results/summary.md
#
# Run:  snakemake --cores 2                        (config/config.yaml)
#       snakemake --cores 2 --configfile my.yaml   (another campaign)

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


# Wildcards of every rule. Scene names: letters, digits, '_' (no '/', so the CDM pattern
# <scene>/a<a>/ never clashes); shards and stack sizes: integers; multipliers: numbers
# as multiplier_label writes them (1, 0.5, 1e-05).
wildcard_constraints:
    scene=r"[A-Za-z][A-Za-z0-9_]*",
    shard=r"[0-9]+",
    n=r"[0-9]+",
    multiplier=r"[0-9]+(\.[0-9]+)?(e[-+]?[0-9]+)?",


include: "workflow/rules/common.smk"
include: "workflow/rules/data.smk"
include: "workflow/rules/gallery.smk"
include: "workflow/rules/simulate.smk"
include: "workflow/rules/domain.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/cdm_grid.smk"
include: "workflow/rules/hst.smk"
include: "workflow/rules/figures.smk"
include: "workflow/rules/summary.smk"


rule all:
    default_target: True
    input:
        all_targets(),
