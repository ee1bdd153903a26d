"""Snakemake script of rule plot_hst_gallery: the figure of the real HST cutouts."""

import logging

from subslope.io.resources import verify_files
from subslope.logs import log_to_file
from subslope.stages.gallery import plot_gallery

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    verify_files(list(snakemake.input))  # the data files as fetched, or a clear error
    plot_gallery(
        snakemake.params.folder,
        [snakemake.output.pdf, snakemake.output.png],
        run_name=snakemake.params.run_name,
        pixel_scale=snakemake.params.pixel_scale,
    )
except Exception:
    logging.exception("plot_hst_gallery failed")
    raise
