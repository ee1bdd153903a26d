# Stage: cdm_grid. Stack MLEs of the simulated CDM sets per concentration multiplier,
# their bands, the sets' effective subhalo slopes (a guide), the matched EPL controls
# and figure 4 (subslope.stages.cdm_grid).


rule effective_slope:
    input:
        shards=[job["path"] for job in SHARD_JOBS if job["scene"] in CDM_SCENES],
    output:
        csv=update("results/measure_cdm_grid/effective_slope.csv"),
    log:
        "logs/effective_slope.log",
    benchmark:
        "results/benchmarks/effective_slope.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=3000,
    params:
        # [scene, multiplier, shard file] of every CDM shard
        groups=[
            [job["scene"], job["multiplier"], job["path"]]
            for job in SHARD_JOBS
            if job["scene"] in CDM_SCENES
        ],
    script:
        "../scripts/effective_slope.py"


# The matched EPL controls (cdm.field_controls, cdm.reference_controls): what EPL
# populations of known slope read on the CDM sets, and their paired shift.
rule measure_epl_control:
    input:
        profiles=[path for group in control_groups() for path in group[3]],
        removed=[path for group in control_groups() for path in group[4]],
    output:
        csv=update("results/measure_cdm_grid/epl_control.csv"),
    log:
        "logs/measure_epl_control.log",
    benchmark:
        "results/benchmarks/measure_epl_control.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        groups=control_groups(),
        band=CDM["band"],
    script:
        "../scripts/measure_epl_control.py"


rule measure_cdm_grid:
    input:
        profiles=cdm_inputs(),
        effective_slopes="results/measure_cdm_grid/effective_slope.csv",
        controls=rules.measure_epl_control.output.csv if CONTROL_SCENES else [],
    output:
        npz=update("results/measure_cdm_grid/cdm_grid.npz"),
        csv=update("results/measure_cdm_grid/cdm_grid.csv"),
        pdf=update("results/figures/fig4_concentration_grid.pdf"),
        png=update(
            report(
                "results/figures/fig4_concentration_grid.png",
                caption="../report/fig4_concentration_grid.rst",
                category="CDM",
            )
        ),
    log:
        "logs/measure_cdm_grid.log",
    benchmark:
        "results/benchmarks/measure_cdm_grid.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        # [scene, multiplier, profiles file] of every CDM shard
        groups=[
            [job["scene"], job["multiplier"], profile_path(job)]
            for job in SHARD_JOBS
            if job["scene"] in CDM_SCENES
        ],
        nfw_scene=CDM["nfw_scene"],
        tnfw_scene=CDM["tnfw_scene"],
        reference_scenes=subslope.config.cdm_grids(config).get("reference"),
        band=CDM["band"],
        run_name=RUN,
    script:
        "../scripts/measure_cdm_grid.py"


# The a = 1 reading against the assumed subhalo abundance (cdm.abundance).
rule measure_abundance:
    input:
        profiles=[path for group in abundance_groups() for path in group[3]],
        removed=[path for group in abundance_groups() for path in group[4]],
    output:
        csv=update("results/measure_cdm_grid/abundance.csv"),
        pdf=update("results/figures/abundance.pdf"),
        png=update("results/figures/abundance.png"),
    log:
        "logs/measure_abundance.log",
    benchmark:
        "results/benchmarks/measure_abundance.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        groups=abundance_groups(),
        band=CDM["band"],
        z_lens=0.2,
        field_arcsec=config["instrument"]["npix"] * config["instrument"]["pixel_scale"],
        run_name=RUN,
    script:
        "../scripts/measure_abundance.py"
