"""Snakemake script of rule summarize_signal_budget: one table and figure of the signal
budget of every scene."""

import logging

from subslope.logs import log_to_file
from subslope.stages.signal_budget import summarize_signal_budget

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    table = summarize_signal_budget(
        snakemake.input.tables,
        snakemake.output.csv,
        [snakemake.output.pdf, snakemake.output.png],
        stack_size=snakemake.params.stack_size,
        run_name=snakemake.params.run_name,
    )
    logging.info("signal budget:\n%s", table.to_string())
except Exception:
    logging.exception("summarize_signal_budget failed")
    raise
