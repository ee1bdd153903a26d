# Stage: inference, calibration, concentration grid and the real lenses.
# Profiles ln r(x|gamma) on the gamma grid for every shard of the evaluation scenes (one
# job per shard, mirroring results/simulate_shard/), thresholds per stack size N (one job
# per N), their coverage, the CDM concentration grid (figure 4) and the HST analysis
# (figures 5, 6). Statistics: subslope.inference / subslope.calibration; glue:
# subslope.campaign; docs/inference.md.

_NUM = r"[0-9]+(\.[0-9]+)?(e[-+]?[0-9]+)?"


rule evaluate_profiles:
    input:
        shard="results/simulate_shard/{scene}/shard_{shard}.h5",
        model=rules.train_estimator.output.model,
    output:
        h5="results/evaluate_profiles/{scene}/shard_{shard}.h5",
    wildcard_constraints:
        scene=SCENE_WILDCARD,
        shard=r"[0-9]+",
    params:
        gamma_grid=GRID,
        batch_size=config["inference"]["batch_size"],
        device=config["inference"]["device"],
        run_name=RUN,
    log:
        "logs/evaluate_profiles/{scene}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/evaluate_profiles/{scene}/shard_{shard}.tsv"
    threads: config["inference"]["threads"]
    resources:
        mem_mb=2000,
        runtime=60,
        gpu=config["inference"]["gpus"],
    conda:
        "../envs/subslope.yaml"
    script:
        "../scripts/evaluate_profiles.py"


use rule evaluate_profiles as evaluate_cdm_profiles with:
    input:
        shard="results/simulate_shard/{scene}/a{multiplier}/shard_{shard}.h5",
        model=rules.train_estimator.output.model,
    output:
        h5="results/evaluate_profiles/{scene}/a{multiplier}/shard_{shard}.h5",
    wildcard_constraints:
        scene=SCENE_WILDCARD,
        shard=r"[0-9]+",
        multiplier=_NUM,
    log:
        "logs/evaluate_profiles/{scene}/a{multiplier}/shard_{shard}.log",
    benchmark:
        "results/benchmarks/evaluate_profiles/{scene}/a{multiplier}/shard_{shard}.tsv"


rule calibrate_threshold:
    input:
        profiles=calibration_inputs,
    output:
        npz="results/calibrate_threshold/N{n}.npz",
    wildcard_constraints:
        n=r"[0-9]+",
    params:
        level=CAL["level"],
        seed=derived_seed("calibration"),
        heldout_fraction=CAL["heldout_fraction"],
    log:
        "logs/calibrate_threshold/N{n}.log",
    benchmark:
        "results/benchmarks/calibrate_threshold/N{n}.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    conda:
        "../envs/subslope.yaml"
    script:
        "../scripts/calibrate_threshold.py"


rule summarize_coverage:
    input:
        npz=expand(rules.calibrate_threshold.output.npz, n=CAL_N),
    output:
        csv="results/summarize_coverage/calibration.csv",
        json="results/summarize_coverage/thresholds.json",
        pdf="results/figures/coverage.pdf",
        png=report(
            "results/figures/coverage.png",
            caption="../report/coverage.rst",
            category="Calibration",
        ),
    params:
        run_name=RUN,
    log:
        "logs/summarize_coverage.log",
    benchmark:
        "results/benchmarks/summarize_coverage.tsv"
    threads: 1
    resources:
        mem_mb=1000,
    conda:
        "../envs/subslope.yaml"
    script:
        "../scripts/summarize_coverage.py"


rule measure_cdm_grid:
    input:
        profiles=cdm_inputs(),
    output:
        npz="results/measure_cdm_grid/cdm_grid.npz",
        csv="results/measure_cdm_grid/cdm_grid.csv",
        pdf="results/figures/fig4_concentration_grid.pdf",
        png=report(
            "results/figures/fig4_concentration_grid.png",
            caption="../report/fig4_concentration_grid.rst",
            category="CDM",
        ),
    params:
        # [scene, multiplier, profiles file] of every CDM shard
        groups=[
            [job["scene"], job["multiplier"], profile_path(job)]
            for job in SHARD_JOBS
            if job["scene"] in (CDM["nfw_scene"], CDM["tnfw_scene"])
        ],
        nfw_scene=CDM["nfw_scene"],
        tnfw_scene=CDM["tnfw_scene"],
        band=CDM["band"],
        run_name=RUN,
    log:
        "logs/measure_cdm_grid.log",
    benchmark:
        "results/benchmarks/measure_cdm_grid.tsv"
    threads: 1
    resources:
        mem_mb=2000,
    conda:
        "../envs/subslope.yaml"
    script:
        "../scripts/measure_cdm_grid.py"


rule analyze_hst:
    input:
        hst=rules.fetch_data.output.hst,
        model=rules.train_estimator.output.model,
        thresholds=rules.summarize_coverage.output.json,
        cdm=rules.measure_cdm_grid.output.csv if STAGE_ON["cdm_grid"] else [],
    output:
        h5="results/analyze_hst/profiles.h5",
        csv="results/analyze_hst/intervals.csv",
        fig5_pdf="results/figures/fig5_hst_profiles.pdf",
        fig5_png=report(
            "results/figures/fig5_hst_profiles.png",
            caption="../report/fig5_hst_profiles.rst",
            category="HST",
        ),
        fig6_pdf="results/figures/fig6_hst_combined.pdf",
        fig6_png=report(
            "results/figures/fig6_hst_combined.png",
            caption="../report/fig6_hst_combined.rst",
            category="HST",
        ),
    params:
        folder=lambda wildcards, input: os.path.dirname(input.hst[0]),
        hst=config["hst"],
        gamma_grid=GRID,
        pixel_scale=config["instrument"]["pixel_scale"],
        device=config["inference"]["device"],
        nfw_scene=CDM["nfw_scene"],
        tnfw_scene=CDM["tnfw_scene"],
        run_name=RUN,
    log:
        "logs/analyze_hst.log",
    benchmark:
        "results/benchmarks/analyze_hst.tsv"
    threads: 1
    resources:
        mem_mb=2000,
    conda:
        "../envs/subslope.yaml"
    script:
        "../scripts/analyze_hst.py"
