"""Snakemake script of rule train_estimator: train (or resume training) the likelihood-ratio
estimator."""

import logging

from subslope.logs import log_to_file
from subslope.stages.train import train_job

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    train_job(
        snakemake.config,
        training=snakemake.params.training,
        train_shards=snakemake.input.train,
        val_shards=snakemake.input.val,
        whitening=snakemake.input.whitening,
        model_path=snakemake.output.model,
        ckpt_dir=snakemake.params.ckpt_dir,
        device=snakemake.params.device,
        stream=snakemake.params.stream,
        stream_data=snakemake.input.stream_data,
        threads=snakemake.threads,
    )
except Exception:
    logging.exception("train_estimator failed")
    raise
