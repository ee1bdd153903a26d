# Stage: evaluate. Profiles ln r(x|gamma) on the gamma grid for every shard of the
# evaluation scenes, one job per shard, mirroring results/simulate_shard/
# (subslope.stages.evaluate; docs/inference.md).


rule evaluate_profiles:
    input:
        shard="results/simulate_shard/{scene}/shard_{shard}.h5",
        model=rules.train_estimator.output.model,
    output:
        h5=update("results/evaluate_profiles/{scene}/shard_{shard}.h5"),
    log:
        "logs/evaluate_profiles/{scene}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/evaluate_profiles/{scene}/shard_{shard}.tsv"
    group:
        "evaluate"
    conda:
        "../envs/subslope.yaml"
    threads: config["inference"]["threads"]
    resources:
        mem_mb=2000,
        runtime=60,
        gpu=config["inference"]["gpus"],
        serial=1,
    params:
        gamma_grid=GRID,
        batch_size=config["inference"]["batch_size"],
        device=config["inference"]["device"],
        run_name=RUN,
    script:
        "../scripts/evaluate_profiles.py"


use rule evaluate_profiles as evaluate_cdm_profiles with:
    input:
        shard="results/simulate_shard/{scene}/a{multiplier}/shard_{shard}.h5",
        model=rules.train_estimator.output.model,
    output:
        h5=update("results/evaluate_profiles/{scene}/a{multiplier}/shard_{shard}.h5"),
    log:
        "logs/evaluate_profiles/{scene}/a{multiplier}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/evaluate_profiles/{scene}/a{multiplier}/shard_{shard}.tsv"
