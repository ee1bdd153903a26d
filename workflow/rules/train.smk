# Stage: training. One estimator trained on the training shards, early-stopped on the
# validation shards (subslope.nre.train). Checkpoints live in
# results/checkpoints/train_estimator/<key>/, which is NOT a declared output: Snakemake
# never deletes it (failed job, walltime kill, --forcerun), so a restarted job resumes
# from last.pt. <key> hashes the training section and the data, so a changed config or
# changed shards start a fresh folder instead of resuming an incompatible run. With
# training.data: stream there are no training shards: the job simulates its images while
# it trains (subslope.nre.stream), from the train scene's resolved config (params.stream).

TRAINING = subslope.stages.train.training_section(config)
CKPT_KEY = subslope.stages.train.checkpoint_key(
    TRAINING,
    shard_files("train"),
    shard_files("validation"),
    {
        scene: simulation_hash(scene)
        for scene in ("train", "validation")
        if shard_files(scene) or (scene == "train" and STREAMING)
    },
)


rule train_estimator:
    input:
        train=lambda wildcards: shard_files("train"),
        val=lambda wildcards: shard_files("validation"),
        whitening=rules.compute_whitening.output.json,
        stream_data=lambda wildcards: (
            [*data_inputs("psf/"), *cosmos_files()] if STREAMING else []
        ),
    output:
        model=update("results/train_estimator/model.pt"),
        log_csv=update("results/train_estimator/training_log.csv"),
    log:
        "logs/train_estimator.log",
    benchmark:
        "results/benchmarks/train_estimator.tsv"
    # Ahead of the remaining shard jobs as soon as its inputs exist: training is the
    # campaign's longest job, the evaluation scenes are simulated beside it.
    priority: 1
    conda:
        "../envs/subslope.yaml"
    # training.ranks processes (torchrun, started by the job itself): a core each at least
    threads: max(config["training"]["threads"], config["training"]["ranks"])
    resources:
        mem_mb=config["training"]["mem_mb"],
        runtime=config["training"]["runtime"],
        # GPU request for cluster executors (SLURM: --gpus); local runs ignore it.
        gpu=config["training"]["gpus"],
        # one task: torchrun inside it starts the ranks (not one SLURM task per GPU)
        tasks=1,
    params:
        training=TRAINING,
        ckpt_dir=f"results/checkpoints/train_estimator/{CKPT_KEY}",
        device=config["training"]["device"],
        stream=stream_job(),
    script:
        "../scripts/train_estimator.py"
