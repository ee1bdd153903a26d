# Stage: hst. Profiles, intervals and figures 5-6 of the real HST lenses
# (subslope.stages.hst).


rule analyze_hst:
    input:
        hst=observation_inputs(),
        model=rules.train_estimator.output.model,
        thresholds=rules.summarize_coverage.output.json,
        cdm=rules.measure_cdm_grid.output.csv if STAGE_ON["cdm_grid"] else [],
        domain=rules.check_domain.output.csv if STAGE_ON["domain"] else [],
    output:
        h5=update("results/analyze_hst/profiles.h5"),
        csv=update("results/analyze_hst/intervals.csv"),
        loo=update("results/analyze_hst/leave_one_out.csv"),
        fig5_pdf=update("results/figures/fig5_hst_profiles.pdf"),
        fig5_png=update(
            report(
                "results/figures/fig5_hst_profiles.png",
                caption="../report/fig5_hst_profiles.rst",
                category="HST",
            )
        ),
        fig6_pdf=update("results/figures/fig6_hst_combined.pdf"),
        fig6_png=update(
            report(
                "results/figures/fig6_hst_combined.png",
                caption="../report/fig6_hst_combined.rst",
                category="HST",
            )
        ),
    log:
        "logs/analyze_hst.log",
    benchmark:
        "results/benchmarks/analyze_hst.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        folder=lambda wildcards, input: observation_source(input.hst),
        hst=config["hst"],
        gamma_grid=GRID,
        pixel_scale=config["instrument"]["pixel_scale"],
        # the detector of the lens-light fit of lens-light-subtracted inputs
        instrument=config["instrument"],
        device=config["inference"]["device"],
        nfw_scene=CDM["nfw_scene"],
        tnfw_scene=CDM["tnfw_scene"],
        reference_scenes=subslope.config.cdm_grids(config).get("reference"),
        run_name=RUN,
    script:
        "../scripts/analyze_hst.py"
