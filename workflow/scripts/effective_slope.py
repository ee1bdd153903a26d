"""Snakemake script of rule effective_slope: the signal-weighted effective subhalo slope of
every simulated CDM set (the reference curve of figure 4)."""

import logging

from subslope.logs import log_to_file
from subslope.stages.cdm_grid import effective_slope_table

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    table = effective_slope_table(snakemake.params.groups, snakemake.output.csv)
    logging.info(
        "effective slopes, median per scene and multiplier:\n%s",
        table.groupby(["scene", "multiplier"])["gamma_eff"].median().to_string(),
    )
except Exception:
    logging.exception("effective_slope failed")
    raise
