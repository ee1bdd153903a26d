# Stage: summary. results/summary.md and the CSVs beside it, from the results of the
# stages that ran (subslope.stages.summary).


rule write_summary:
    input:
        unpack(summary_inputs),
    output:
        md=update("results/summary.md"),
        run=update("results/run.json"),
        response_pdf=update("results/figures/response.pdf"),
        response_png=update("results/figures/response.png"),
        csv=update(expand("results/{name}.csv", name=SUMMARY_CSVS)),
    log:
        "logs/write_summary.log",
    conda:
        "../envs/subslope.yaml"
    threads: 1
    params:
        run_name=RUN,
        config_hash=CONFIG_HASH,
        config_files=CONFIG_FILES,
        benchmarks=benchmark_files(),
        nfw_scene=CDM["nfw_scene"],
        tnfw_scene=CDM["tnfw_scene"],
        reference_scenes=subslope.config.cdm_grids(config).get("reference"),
        highlight=config["hst"]["highlight"],
    script:
        "../scripts/write_summary.py"
