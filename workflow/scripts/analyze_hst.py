"""Snakemake script of rule analyze_hst: profiles, intervals and figures 5-6 of the real HST
lenses."""

import logging

import torch

from subslope.devices import pick_device
from subslope.io.resources import verify_files
from subslope.logs import log_to_file
from subslope.stages.hst import analyze_hst
from subslope.stats.intervals import gamma_grid

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    pick_device(
        snakemake.params.device, key="inference.device"
    )  # a device this machine lacks fails here
    verify_files(list(snakemake.input))  # the data files as fetched, or a clear error
    torch.set_num_threads(snakemake.threads)
    hst = snakemake.params.hst
    grid = snakemake.params.gamma_grid
    table = analyze_hst(
        snakemake.input.model,
        snakemake.params.folder,
        snakemake.input.thresholds,
        snakemake.output.h5,
        snakemake.output.csv,
        snakemake.output.fig5_pdf[: -len(".pdf")],
        snakemake.output.fig6_pdf[: -len(".pdf")],
        run_name=snakemake.params.run_name,
        gammas=gamma_grid(grid["low"], grid["high"], grid["n"]),
        cdm_csv=snakemake.input.cdm or None,
        combine=hst["combine"],
        show=hst["show"],
        highlight=hst["highlight"],
        lens_centre=hst["lens_centre"],
        pixel_scale=snakemake.params.pixel_scale,
        device=snakemake.params.device,
        nfw_scene=snakemake.params.nfw_scene,
        tnfw_scene=snakemake.params.tnfw_scene,
        reference_scenes=snakemake.params.reference_scenes,
        domain_csv=snakemake.input.domain or None,
        config=snakemake.config,
        loo_csv=snakemake.output.loo,
    )
    logging.info("intervals:\n%s", table.to_string())
except Exception:
    logging.exception("analyze_hst failed")
    raise
