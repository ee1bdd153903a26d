# Stage: calibrate. The threshold tau_N of every stack size N (one job per N) and their
# held-out coverage (subslope.stages.calibrate; statistics in subslope.stats).


rule calibrate_threshold:
    input:
        profiles=calibration_inputs,
    output:
        npz=update("results/calibrate_threshold/N{n}.npz"),
    log:
        "logs/calibrate_threshold/N{n}.log",
    benchmark:
        "results/benchmarks/calibrate_threshold/N{n}.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    params:
        level=CAL["level"],
        seed=derived_seed("calibration"),
        heldout_fraction=CAL["heldout_fraction"],
        stacks=CAL["stacks"],
    script:
        "../scripts/calibrate_threshold.py"


rule summarize_coverage:
    input:
        npz=expand(rules.calibrate_threshold.output.npz, n=CAL_N),
    output:
        csv=update("results/summarize_coverage/calibration.csv"),
        json=update("results/summarize_coverage/thresholds.json"),
        pdf=update("results/figures/coverage.pdf"),
        png=update(
            report(
                "results/figures/coverage.png",
                caption="../report/coverage.rst",
                category="Calibration",
            )
        ),
    log:
        "logs/summarize_coverage.log",
    benchmark:
        "results/benchmarks/summarize_coverage.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=1000,
    params:
        run_name=RUN,
    script:
        "../scripts/summarize_coverage.py"
