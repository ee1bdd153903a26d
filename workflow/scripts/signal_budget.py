"""Snakemake script of rules signal_budget and signal_budget_cdm: the Delta chi^2 of the
subhalos of the first images of one shard."""

import logging

from subslope.logs import log_to_file
from subslope.render.kernels import use_compile_cache
from subslope.simulation.sources import cosmos_folders
from subslope.stages.signal_budget import signal_budget_shard

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    use_compile_cache(snakemake.config["simulation"]["render"].get("compile_cache"))
    signal_budget_shard(
        snakemake.input.shard,
        snakemake.output.csv,
        snakemake.params.images,
        mask_factor=snakemake.params.mask_factor,
        scene=snakemake.wildcards.scene,
        multiplier=snakemake.wildcards.get("multiplier"),
        cosmos=[str(f) for f in cosmos_folders(snakemake.config)],
        iterations=snakemake.params.iterations,
    )
except Exception:
    logging.exception("signal_budget failed")
    raise
