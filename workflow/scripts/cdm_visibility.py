"""Snakemake script of rule cdm_visibility: the stack gamma_MLE of the CDM sets of every
multiplier with and without their subhalos, set by set."""

import logging

from subslope.logs import log_to_file
from subslope.stages.null_tests.visibility import cdm_visibility

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    files = {}
    for scene, multiplier, original, removed in snakemake.params.groups:
        pair = files.setdefault((scene, float(multiplier)), ([], []))
        pair[0].append(original)
        pair[1].append(removed)
    table = cdm_visibility(files, snakemake.output.csv)
    logging.info("visibility:\n%s", table.to_string())
except Exception:
    logging.exception("cdm_visibility failed")
    raise
