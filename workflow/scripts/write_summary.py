"""Snakemake script of rule write_summary: results/summary.md and the CSVs beside it."""

import json
import logging

from subslope.logs import log_to_file
from subslope.stages.summary import write_run_record, write_summary

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    inputs = snakemake.input
    trend = None
    if "trend" in inputs.keys():
        with open(inputs.trend, encoding="utf-8") as fh:
            trend = json.load(fh)
    path = write_summary(
        snakemake.output.md,
        run_name=snakemake.params.run_name,
        config_hash=snakemake.params.config_hash,
        config_file=", ".join(snakemake.params.config_files),
        hst_csv=inputs.get("hst"),
        loo_csv=inputs.get("leave_one_out"),
        cdm_csv=inputs.get("cdm"),
        calibration_csv=inputs.get("calibration"),
        domain_csv=inputs.get("domain"),
        null_csv=inputs.get("null_tests"),
        halo_free_csv=inputs.get("halo_free"),
        bias_csv=inputs.get("nsub_bias"),
        visibility_csv=inputs.get("cdm_visibility"),
        signal_csv=inputs.get("signal_budget"),
        seeds_csv=inputs.get("seeds"),
        trend=trend,
        benchmarks=snakemake.params.benchmarks,
        nfw_scene=snakemake.params.nfw_scene,
        tnfw_scene=snakemake.params.tnfw_scene,
        reference_scenes=snakemake.params.reference_scenes,
        control_csv=inputs.get("epl_control"),
        contrast_csv=inputs.get("contrast"),
        abundance_csv=inputs.get("abundance"),
        classifier_json=list(inputs.get("classifier") or []),
        highlight=snakemake.params.highlight,
    )
    record = write_run_record(
        snakemake.output.run,
        run_name=snakemake.params.run_name,
        config_hash=snakemake.params.config_hash,
        config_files=snakemake.params.config_files,
    )
    logging.info("wrote %s and %s", path, record)
except Exception:
    logging.exception("write_summary failed")
    raise
