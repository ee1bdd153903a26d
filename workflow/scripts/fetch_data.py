"""Snakemake script of rule fetch_data: copy/download and verify the data resources."""

import logging

from subslope.logs import log_to_file
from subslope.stages.data import fetch_files

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    fetch_files(
        snakemake.output,
        mirror=snakemake.config["data"]["mirror"],
        allow_download=snakemake.config["data"]["allow_download"],
    )
except Exception:
    logging.exception("fetch_data failed")
    raise
