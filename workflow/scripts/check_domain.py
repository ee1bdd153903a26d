"""Snakemake script of rule check_domain: simulated vs HST summary statistics."""

import logging
import os

from subslope.io.resources import verify_files
from subslope.logs import log_to_file
from subslope.nre.preprocess import read_whitening
from subslope.stages.domain import check_domain, shard_images

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    verify_files(list(snakemake.input))  # the data files as fetched, or a clear error
    images, theta_e = shard_images(list(snakemake.input.shards), snakemake.params.n_images)
    check_domain(
        snakemake.config,
        images,
        theta_e,
        read_whitening(snakemake.input.whitening),
        snakemake.params.folder,
        os.path.dirname(snakemake.output.csv),
        [str(snakemake.output[k])[: -len(".pdf")] for k in ("pdf", "gallery_pdf", "sources_pdf")],
        scene=snakemake.params.scene,
    )
except Exception:
    logging.exception("check_domain failed")
    raise
