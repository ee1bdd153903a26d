# Stage: figures. Training curves and figures 2-3 with the estimator trend
# (subslope.stages.figures).


rule plot_training_curves:
    input:
        log_csv=rules.train_estimator.output.log_csv,
    output:
        pdf=update("results/figures/training_curves.pdf"),
        png=update(
            report(
                "results/figures/training_curves.png",
                caption="../report/training_curves.rst",
                category="Training",
            )
        ),
    log:
        "logs/plot_training_curves.log",
    benchmark:
        "results/benchmarks/plot_training_curves.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    params:
        run_name=RUN,
    script:
        "../scripts/plot_training_curves.py"


rule plot_validation:
    input:
        single=lambda wildcards: profile_files(CAL["single_scene"]),
        stacks=lambda wildcards: profile_files(CAL["stack_scene"]),
        thresholds=rules.summarize_coverage.output.json,
    output:
        trend=update("results/plot_validation/trend.json"),
        fig2_pdf=update("results/figures/fig2_validation.pdf"),
        fig2_png=update(
            report(
                "results/figures/fig2_validation.png",
                caption="../report/fig2_validation.rst",
                category="Validation",
            )
        ),
        fig3_pdf=update("results/figures/fig3_stacks.pdf"),
        fig3_png=update(
            report(
                "results/figures/fig3_stacks.png",
                caption="../report/fig3_stacks.rst",
                category="Validation",
            )
        ),
    log:
        "logs/plot_validation.log",
    benchmark:
        "results/benchmarks/plot_validation.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    params:
        run_name=RUN,
    script:
        "../scripts/plot_validation.py"
