"""Snakemake script of rule fit_lens_light: Sérsic fits of the HST lens light."""

import logging

from subslope.io.resources import verify_files
from subslope.logs import log_to_file
from subslope.stages.domain import fit_hst_lens_light_job

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    verify_files(list(snakemake.input))  # the data files as fetched, or a clear error
    table = fit_hst_lens_light_job(
        snakemake.config, snakemake.params.folder, snakemake.output.csv, snakemake.output.prior
    )
    logging.info("fitted the lens light of %d lenses", len(table))
except Exception:
    logging.exception("fit_lens_light failed")
    raise
