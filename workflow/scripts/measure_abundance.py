"""Snakemake script of rule measure_abundance: the a = 1 reading and paired shift of the
CDM sets against the largest subhalo count of their prior, and its figure."""

import logging

from subslope.logs import log_to_file
from subslope.stages.cdm_grid import measure_abundance

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    table = measure_abundance(
        snakemake.params.groups,
        snakemake.output.csv,
        snakemake.output.pdf[: -len(".pdf")],
        z_lens=snakemake.params.z_lens,
        field_arcsec=snakemake.params.field_arcsec,
        run_name=snakemake.params.run_name,
        band=tuple(snakemake.params.band),
    )
    logging.info("abundance:\n%s", table.to_string())
except Exception:
    logging.exception("measure_abundance failed")
    raise
