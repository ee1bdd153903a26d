"""Snakemake script of rule plot_scene_examples: example images of one scene."""

import logging

from subslope.logs import log_to_file
from subslope.stages.simulate import plot_scene_examples_from_shard

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    shown = plot_scene_examples_from_shard(
        snakemake.input.shard,
        [snakemake.output.png],
        run_name=snakemake.params.run_name,
        n=snakemake.params.n_examples,
        cosmos=snakemake.params.cosmos,
    )
    logging.info("plotted images %s of %s", shown, snakemake.input.shard)
except Exception:
    logging.exception("plot_scene_examples failed")
    raise
