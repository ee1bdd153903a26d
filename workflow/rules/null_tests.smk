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


# The null test a gamma-blind estimator must pass (subslope.stages.null_tests.halo_free): the first
# null_tests.halo_free_sets sets of the stack scene re-rendered without their subhalos
# and line-of-sight halos, their negative sheets kept and removed; gamma_MLE must not
# follow the label. Also the bias of gamma_MLE by N_sub. Off when halo_free_sets is 0.
rule halo_free_profiles:
    input:
        shard="results/simulate_shard/{scene}/shard_{shard}.h5",
        model=rules.train_estimator.output.model,
    output:
        sheets_kept=update(
            "results/null_tests/halo_free/sheets_kept/{scene}/shard_{shard}.h5"
        ),
        sheets_removed=update(
            "results/null_tests/halo_free/sheets_removed/{scene}/shard_{shard}.h5"
        ),
    log:
        "logs/halo_free_profiles/{scene}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/halo_free_profiles/{scene}/shard_{shard}.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: config["inference"]["threads"]
    resources:
        mem_mb=3000,
        runtime=60,
        gpu=config["inference"]["gpus"],
        serial=1,
    params:
        gamma_grid=GRID,
        batch_size=config["inference"]["batch_size"],
        device=config["inference"]["device"],
        run_name=RUN,
    script:
        "../scripts/halo_free_profiles.py"


rule halo_free_null:
    input:
        original=[profile_path(job) for job in HALO_FREE_JOBS],
        sheets_kept=halo_free_files("sheets_kept"),
        sheets_removed=halo_free_files("sheets_removed"),
        shards=[job["path"] for job in HALO_FREE_JOBS],
    output:
        csv=update("results/null_tests/halo_free.csv"),
        bias=update("results/null_tests/nsub_bias.csv"),
        sheet=update("results/null_tests/sheet_channel.csv"),
    log:
        "logs/halo_free_null.log",
    benchmark:
        "results/benchmarks/halo_free_null.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        n_sets=subslope.config.halo_free_sets(config),
    script:
        "../scripts/halo_free_null.py"


# Do the CDM subhalos reach the estimator? The shards of the CDM scenes (every multiplier) re-rendered
# without their subhalos (line-of-sight halos, lens, source, light and noise seeds as
# stored), and each set's stack gamma_MLE compared with its original's
# (subslope.stages.null_tests.visibility). Off with null_tests.cdm_visibility: false.
use rule halo_free_profiles as subhalo_free_profiles with:
    input:
        shard="results/simulate_shard/{scene}/a{multiplier}/shard_{shard}.h5",
        model=rules.train_estimator.output.model,
    output:
        subhalos_removed=update(
            "results/null_tests/subhalo_free/{scene}/a{multiplier}/shard_{shard}.h5"
        ),
    log:
        "logs/subhalo_free_profiles/{scene}/a{multiplier}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/subhalo_free/{scene}/a{multiplier}/shard_{shard}.tsv"
    group:
        "evaluate"


rule cdm_visibility:
    input:
        original=[profile_path(job) for job in VISIBILITY_JOBS],
        removed=[subhalo_free_path(job) for job in VISIBILITY_JOBS],
    output:
        csv=update("results/null_tests/cdm_visibility.csv"),
    log:
        "logs/cdm_visibility.log",
    benchmark:
        "results/benchmarks/cdm_visibility.tsv"
    conda:
        "../envs/subslope.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    params:
        # [scene, multiplier, profiles file, re-rendered profiles file] of every CDM shard
        groups=[
            [
                job["scene"],
                job["multiplier"],
                profile_path(job),
                subhalo_free_path(job),
            ]
            for job in VISIBILITY_JOBS
        ],
    script:
        "../scripts/cdm_visibility.py"
