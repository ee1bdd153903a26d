"""Snakemake script of rules simulate_shard / simulate_cdm_shard: one shard of images."""

import logging

from subslope.io.resources import verify_files
from subslope.logs import log_to_file
from subslope.stages.simulate import simulate_shard_job

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    verify_files(list(snakemake.input))  # the data files as fetched, or a clear error
    multiplier = snakemake.wildcards.get("multiplier")
    simulate_shard_job(
        snakemake.params.job,
        snakemake.config,
        snakemake.wildcards.scene,
        int(snakemake.wildcards.shard),
        snakemake.output.h5,
        multiplier=None if multiplier is None else float(multiplier),
        threads=snakemake.threads,
    )
except Exception:
    logging.exception("simulate_shard failed")
    raise
