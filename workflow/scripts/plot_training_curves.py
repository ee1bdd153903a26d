"""Snakemake script of rule plot_training_curves: loss curves of the estimator training."""

import logging

from subslope.logs import log_to_file
from subslope.stages.figures import plot_training_curves

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    plot_training_curves(
        snakemake.input.log_csv,
        snakemake.output.pdf[: -len(".pdf")],
        run_name=snakemake.params.run_name,
    )
except Exception:
    logging.exception("plot_training_curves failed")
    raise
