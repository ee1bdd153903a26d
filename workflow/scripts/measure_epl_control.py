"""Snakemake script of rule measure_epl_control: the stack MLEs of the matched EPL
controls and their paired shift."""

import logging

from subslope.logs import log_to_file
from subslope.stages.cdm_grid import measure_epl_control

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    table = measure_epl_control(
        snakemake.params.groups, snakemake.output.csv, band=tuple(snakemake.params.band)
    )
    logging.info("matched EPL controls:\n%s", table.to_string())
except Exception:
    logging.exception("measure_epl_control failed")
    raise
