"""Snakemake script of rule concentration_contrast: the refitted Delta chi^2 between the
images of one draw at two concentration multipliers."""

import logging

from subslope.logs import log_to_file
from subslope.render.kernels import use_compile_cache
from subslope.simulation.sources import cosmos_folders
from subslope.stages.signal_budget import concentration_contrast

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    use_compile_cache(snakemake.config["simulation"]["render"].get("compile_cache"))
    concentration_contrast(
        snakemake.params.groups,
        snakemake.output.csv,
        snakemake.params.images,
        mask_factor=snakemake.params.mask_factor,
        cosmos=[str(f) for f in cosmos_folders(snakemake.config)],
        iterations=snakemake.params.iterations,
    )
except Exception:
    logging.exception("concentration_contrast failed")
    raise
