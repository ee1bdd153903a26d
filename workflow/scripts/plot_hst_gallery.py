"""Snakemake script of rule plot_hst_gallery: the figure of the real HST cutouts."""

import logging

from subslope.observations import load_hst
from subslope.plotting import plot_hst_gallery
from subslope.logs import log_to_file

log_to_file(snakemake.log[0])
try:
    observations = load_hst(snakemake.params.folder)
    logging.info("loaded %d cutouts: %s", len(observations), [o.name for o in observations])
    plot_hst_gallery(
        observations,
        [snakemake.output.pdf, snakemake.output.png],
        run_name=snakemake.params.run_name,
        pixel_scale=snakemake.params.pixel_scale,
    )
except Exception:
    logging.exception("plot_hst_gallery failed")
    raise
