"""Snakemake script of rule halo_free_null: the halo-free null test and the bias of
gamma_MLE by N_sub."""

import logging

from subslope.logs import log_to_file
from subslope.stages.null_tests.halo_free import halo_free_null

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    inp = snakemake.input
    halo_free_null(
        list(inp.original),
        {"sheets_kept": list(inp.sheets_kept), "sheets_removed": list(inp.sheets_removed)},
        list(inp.shards),
        snakemake.output.csv,
        snakemake.output.bias,
        snakemake.output.sheet,
        n_sets=snakemake.params.n_sets,
    )
except Exception:
    logging.exception("halo_free_null failed")
    raise
