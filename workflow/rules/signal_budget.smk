# Stage: signal_budget. The ideal observer's signal of every simulated scene: the first
# signal_budget.images images of shard 0 re-rendered noise-free with and without their
# subhalos, and the Delta chi^2 of the difference with the smooth model fixed, after a
# linearised refit and after a full refit (subslope.stages.signal_budget). The
# validation scene is left out.


rule signal_budget:
    input:
        shard="results/simulate_shard/{scene}/shard_{shard}.h5",
    output:
        csv=update("results/signal_budget/{scene}/shard_{shard}.csv"),
    log:
        "logs/signal_budget/{scene}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/signal_budget/{scene}/shard_{shard}.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=60,
    params:
        images=config["signal_budget"]["images"],
        mask_factor=config["training"]["mask_factor"],
        iterations=config["signal_budget"]["refit_iterations"],
    script:
        "../scripts/signal_budget.py"


use rule signal_budget as signal_budget_cdm with:
    input:
        shard="results/simulate_shard/{scene}/a{multiplier}/shard_{shard}.h5",
    output:
        csv=update("results/signal_budget/{scene}/a{multiplier}/shard_{shard}.csv"),
    log:
        "logs/signal_budget/{scene}/a{multiplier}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/signal_budget/{scene}/a{multiplier}/shard_{shard}.tsv"


rule summarize_signal_budget:
    input:
        tables=[budget_path(job) for job in budget_jobs()],
    output:
        csv=update("results/signal_budget/signal_budget.csv"),
        pdf=update("results/figures/signal_budget.pdf"),
        png=update("results/figures/signal_budget.png"),
    log:
        "logs/summarize_signal_budget.log",
    benchmark:
        "results/benchmarks/summarize_signal_budget.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=1000,
    params:
        stack_size=config["signal_budget"]["stack_size"],
        run_name=RUN,
    script:
        "../scripts/summarize_signal_budget.py"


# How much the images can say about the concentration, from above: the refitted Delta
# chi^2 between the a_high and the a_low image of the same draw (signal_budget.contrast).
rule concentration_contrast:
    input:
        shards=[path for group in contrast_groups() for path in group[3:]],
    output:
        csv=update("results/signal_budget/concentration_contrast.csv"),
    log:
        "logs/concentration_contrast.log",
    benchmark:
        "results/benchmarks/concentration_contrast.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=120,
    params:
        groups=contrast_groups(),
        images=config["signal_budget"]["images"],
        mask_factor=config["training"]["mask_factor"],
        iterations=config["signal_budget"]["refit_iterations"],
    script:
        "../scripts/concentration_contrast.py"
