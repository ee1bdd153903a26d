"""Snakemake script of rule compute_whitening: pixel mean/std of the training shards."""

import logging

from subslope.logs import log_to_file
from subslope.stages.simulate import compute_whitening

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    result = compute_whitening(
        snakemake.config, list(snakemake.input.shards), snakemake.output.json
    )
    logging.info(
        "%s inputs: mean %.6g, std %.6g over %d images of %d shards",
        result["inputs"]["kind"],
        result["mean"],
        result["std"],
        result["n_images"],
        len(result["shards"]),
    )
except Exception:
    logging.exception("compute_whitening failed")
    raise
