"""Snakemake script of rule calibrate_threshold: threshold tau_N and held-out coverage for stacks
of N images."""

import logging

from subslope.logs import log_to_file
from subslope.stages.calibrate import calibrate_stack_size

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    out = calibrate_stack_size(
        list(snakemake.input.profiles),
        int(snakemake.wildcards.n),
        snakemake.output.npz,
        level=snakemake.params.level,
        seed=snakemake.params.seed,
        heldout_fraction=snakemake.params.heldout_fraction,
        stacks=snakemake.params.stacks,
    )
    if not out["tau_exact"]:
        logging.warning(
            "too few stacks (%d) for a conformal threshold at level %g: tau = max t",
            out["t_true"].size,
            out["level"],
        )
except Exception:
    logging.exception("calibrate_threshold failed")
    raise
