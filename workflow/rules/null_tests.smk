# Stage: null_tests. Scenes without subhalos through the calibrated inference: the
# spread of gamma_MLE, the mean profile and the intervals that exclude part of the prior
# (subslope.stages.null_tests). Nothing runs when null_tests.scenes is empty.

NULL_SCENES = config["null_tests"]["scenes"]


rule null_tests:
    input:
        profiles=[
            profile_path(job) for job in SHARD_JOBS if job["scene"] in NULL_SCENES
        ],
        thresholds=rules.summarize_coverage.output.json,
    output:
        csv=update("results/null_tests/null_tests.csv"),
        pdf=update("results/figures/null_tests.pdf"),
        png=update(
            report(
                "results/figures/null_tests.png",
                caption="../report/null_tests.rst",
                category="Validation",
            )
        ),
    log:
        "logs/null_tests.log",
    benchmark:
        "results/benchmarks/null_tests.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        groups=[
            [job["scene"], profile_path(job)]
            for job in SHARD_JOBS
            if job["scene"] in NULL_SCENES
        ],
        run_name=RUN,
    script:
        "../scripts/null_tests.py"
