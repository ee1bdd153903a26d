"""Snakemake script of rule evaluate_profiles: ln r on the gamma grid for every image of one shard
(also evaluate_cdm_profiles)."""

import logging

import torch

from subslope.devices import pick_device
from subslope.logs import log_to_file
from subslope.stages.evaluate import evaluate_shard
from subslope.stats.intervals import gamma_grid

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    pick_device(
        snakemake.params.device, key="inference.device"
    )  # a device this machine lacks fails here
    torch.set_num_threads(snakemake.threads)
    grid = snakemake.params.gamma_grid
    path = evaluate_shard(
        snakemake.input.model,
        snakemake.input.shard,
        snakemake.output.h5,
        gammas=gamma_grid(grid["low"], grid["high"], grid["n"]),
        batch_size=snakemake.params.batch_size,
        device=snakemake.params.device,
        run_name=snakemake.params.run_name,
    )
    logging.info("wrote %s", path)
except Exception:
    logging.exception("evaluate_profiles failed")
    raise
