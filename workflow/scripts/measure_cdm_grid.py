"""Snakemake script of rule measure_cdm_grid: stack MLEs of the NFW/tNFW sets per multiplier and
figure 4."""

import logging

from subslope.logs import log_to_file
from subslope.stages.cdm_grid import measure_cdm_grid

log_to_file(snakemake.log[0], outputs=snakemake.output, params=snakemake.params)
try:
    files = {}
    for scene, multiplier, path in snakemake.params.groups:
        files.setdefault((scene, float(multiplier)), []).append(path)
    table = measure_cdm_grid(
        files,
        snakemake.output.npz,
        snakemake.output.csv,
        snakemake.output.pdf[: -len(".pdf")],
        run_name=snakemake.params.run_name,
        nfw_scene=snakemake.params.nfw_scene,
        tnfw_scene=snakemake.params.tnfw_scene,
        reference_scenes=snakemake.params.reference_scenes,
        band=tuple(snakemake.params.band),
        effective_slopes_csv=snakemake.input.effective_slopes,
        control_csv=snakemake.input.controls or None,
    )
    logging.info("concentration grid:\n%s", table.to_string())
except Exception:
    logging.exception("measure_cdm_grid failed")
    raise
