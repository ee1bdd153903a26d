"""Snakemake script of rules halo_free_profiles and subhalo_free_profiles: ln r on the gamma
grid of one shard's images re-rendered without their halos, one profiles file per named
output (sheets_kept, sheets_removed, subhalos_removed)."""

import logging

import torch

from subslope.devices import pick_device
from subslope.logs import log_to_file
from subslope.render.kernels import use_compile_cache
from subslope.stages.null_tests.halo_free import halo_free_shard
from subslope.stats.intervals import gamma_grid

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    pick_device(snakemake.params.device, key="inference.device")
    use_compile_cache(snakemake.config["simulation"]["render"].get("compile_cache"))
    torch.set_num_threads(snakemake.threads)
    grid = snakemake.params.gamma_grid
    written = halo_free_shard(
        snakemake.config,
        snakemake.input.model,
        snakemake.input.shard,
        {v: snakemake.output[v] for v in snakemake.output.keys()},
        gammas=gamma_grid(grid["low"], grid["high"], grid["n"]),
        batch_size=snakemake.params.batch_size,
        device=snakemake.params.device,
        run_name=snakemake.params.run_name,
    )
    logging.info("wrote %s", written)
except Exception:
    logging.exception("halo_free_profiles failed")
    raise
