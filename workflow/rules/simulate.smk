# Stage: simulation. Shards of simulated images per scene (and per concentration
# multiplier for the CDM scenes), the whitening statistics of the training shards and
# one figure of example images per scene. Shards are valuable (hours of compute at
# campaign scale): never temp(). Which shards exist comes from
# subslope.plan.shard_jobs(config) (counts in config["simulation"]["scenes"]).


rule simulate_shard:
    input:
        psf=data_inputs("psf/"),
        cosmos=cosmos_files(),
    output:
        h5=update("results/simulate_shard/{scene}/shard_{shard}.h5"),
    log:
        "logs/simulate_shard/{scene}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/simulate_shard/{scene}/shard_{shard}.tsv"
    # The shards training waits for first: training then runs on one core while the
    # other simulates the evaluation scenes (the campaign's critical path).
    priority: shard_priority
    group:
        "simulate"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=120,
        serial=1,
    params:
        # The resolved values that determine this shard's images: a change of any of
        # them reruns the job, and nothing else does (subslope.plan.shard_job_config).
        job=shard_job,
    script:
        "../scripts/simulate_shard.py"


use rule simulate_shard as simulate_cdm_shard with:
    output:
        h5=update("results/simulate_shard/{scene}/a{multiplier}/shard_{shard}.h5"),
    log:
        "logs/simulate_shard/{scene}/a{multiplier}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/simulate_shard/{scene}/a{multiplier}/shard_{shard}.tsv"


rule compute_whitening:
    input:
        shards=lambda wildcards: whitening_shards(),
    output:
        json=update("results/compute_whitening/whitening.json"),
    log:
        "logs/compute_whitening.log",
    benchmark:
        "results/benchmarks/compute_whitening.tsv"
    priority: 1
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        # the input transform the statistics are measured after: a change reruns the job
        inputs=lambda wildcards: {
            "inputs": config["training"]["inputs"],
            "instrument": config["instrument"],
        },
    script:
        "../scripts/compute_whitening.py"


rule plot_scene_examples:
    input:
        shard=lambda wildcards: example_shard(wildcards.scene),
        cosmos=cosmos_files(),
    output:
        png=update(
            report(
                "results/figures/scene_examples_{scene}.png",
                caption="../report/scene_examples.rst",
                category="Simulation",
            )
        ),
    log:
        "logs/plot_scene_examples/{scene}.log",
    conda:
        "../envs/subslope.yaml"
    threads: 1
    params:
        run_name=config["run_name"],
        n_examples=8,
        cosmos=lambda wildcards, input: cosmos_dirs(input.cosmos),
    script:
        "../scripts/plot_scene_examples.py"
