"""Snakemake script of rule plot_validation: figures 2 (single images) and 3 (stacks), and the
Spearman trend."""

import json
import logging

from subslope.logs import log_to_file
from subslope.stages.figures import plot_validation

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    trend = plot_validation(
        list(snakemake.input.single),
        list(snakemake.input.stacks),
        snakemake.input.thresholds,
        snakemake.output.fig2_pdf[: -len(".pdf")],
        snakemake.output.fig3_pdf[: -len(".pdf")],
        run_name=snakemake.params.run_name,
    )
    with open(snakemake.output.trend, "w", encoding="utf-8") as fh:
        json.dump(trend, fh, indent=2)
    logging.info("Spearman trend of the stack MLEs: %s", trend)
except Exception:
    logging.exception("plot_validation failed")
    raise
