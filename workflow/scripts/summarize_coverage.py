"""Snakemake script of rule summarize_coverage: calibration table, thresholds per N and the
coverage figure."""

import logging

from subslope.logs import log_to_file
from subslope.stages.calibrate import summarize_coverage

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    table, thresholds = summarize_coverage(
        list(snakemake.input.npz),
        snakemake.output.csv,
        snakemake.output.json,
        snakemake.output.pdf[: -len(".pdf")],
        run_name=snakemake.params.run_name,
    )
    logging.info("calibration table:\n%s", table.to_string())
except Exception:
    logging.exception("summarize_coverage failed")
    raise
