"""Snakemake script of rule train_estimator: train (or resume training) the likelihood-ratio
estimator."""

import logging
import os

import torch

from subslope.devices import pick_device
from subslope.io.resources import verify_files
from subslope.logs import log_to_file
from subslope.stages.simulate import runnable_config
from subslope.stages.train import run_training

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    pick_device(
        snakemake.params.device, key="training.device"
    )  # a device this machine lacks fails here
    torch.set_num_threads(snakemake.threads)
    logging.info(
        "checkpoints in %s (kept across reruns; a restarted job resumes)", snakemake.params.ckpt_dir
    )
    stream = snakemake.params.stream
    if stream is not None:  # training.data: stream
        verify_files(list(snakemake.input.stream_data))
        stream = runnable_config(stream, snakemake.config)
    summary = run_training(
        snakemake.params.training,
        list(snakemake.input.train),
        list(snakemake.input.val),
        snakemake.input.whitening,
        os.path.dirname(snakemake.output.model),
        snakemake.params.ckpt_dir,
        device=snakemake.params.device,
        stream=stream,
        # not a param: the number of processes does not change the training
        ranks=snakemake.config["training"]["ranks"],
    )
    logging.info("training done: %s", summary)
except Exception:
    logging.exception("train_estimator failed")
    raise
