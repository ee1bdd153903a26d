"""Snakemake script of rule null_tests: the null scenes through the calibrated inference."""

import logging

from subslope.logs import log_to_file
from subslope.stages.null_tests import null_tests

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    files = {}
    for scene, path in snakemake.params.groups:
        files.setdefault(scene, []).append(path)
    table = null_tests(
        files,
        snakemake.input.thresholds,
        snakemake.output.csv,
        snakemake.output.pdf[: -len(".pdf")],
        run_name=snakemake.params.run_name,
    )
    logging.info("null tests:\n%s", table.to_string())
except Exception:
    logging.exception("null_tests failed")
    raise
