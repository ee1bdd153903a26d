# Shared set-up: configuration validation and helpers used by every stage.

import glob
import os
import re

from snakemake.logging import logger
from snakemake.exceptions import WorkflowError

import subslope.devices
import subslope.logs
import subslope.io.atomic
import subslope.plan
import subslope.config
import subslope.io.resources
import subslope.io.observation_set
import subslope.simulation.resolve
import subslope.stages.train

# Validate once, when the workflow loads: the schema (types, ranges, defaults filled
# in) and every cross-key check, with messages that name the key and what is allowed.
# workflow/schemas/config.schema.yaml links to the same schema for `snakemake --lint`.
try:
    config.update(subslope.config.validate(config))
except subslope.config.ConfigError as exc:
    raise WorkflowError(str(exc)) from None
subslope.config.apply_env_overrides(config)  # SUBSLOPE_DATA_MIRROR -> data.mirror
# What only the scenes, the data registry and the HST catalogue show, before any job.
_PROBLEMS = subslope.plan.plan_problems(config)
if _PROBLEMS:
    raise WorkflowError("invalid configuration:\n  - " + "\n  - ".join(_PROBLEMS))
if workflow.is_main_process:
    for _warning in subslope.plan.plan_warnings(config):
        logger.warning(f"warning: {_warning}")
# Outputs of jobs that started and did not finish (killed, or failed and restored by
# update()) are made older than any input, so that their jobs run again
# (subslope.logs). Only the main process: a cluster job's own Snakemake leaves the
# records of the jobs running beside it alone.
if workflow.is_main_process:
    # A data file deleted after it was fetched is put back here, not by fetch_data, so
    # that none of its readers runs again (subslope.io.resources.restore_deleted); a
    # fetch of it that failed meanwhile is done with.
    _RESTORED = subslope.io.resources.restore_deleted(
        config["data"]["resources_dir"], mirror=config["data"]["mirror"]
    )
    for _data in _RESTORED:
        logger.info(f"{_data} was deleted; restored from the data mirror")
    subslope.logs.forget_jobs_of(_RESTORED)
    for _stale in subslope.logs.mark_unfinished_outputs():
        logger.warning(f"{_stale}: its last job did not finish; that job runs again")
    for _tmp in subslope.io.atomic.remove_stale_temporaries_under("results"):
        logger.info(f"removed {_tmp}, left by a killed job")


# Before the first job, once the executor is known: a device this machine cannot serve
# (training.device: cuda without CUDA) on a local run, where the jobs run here; GPU
# requests on a SLURM cluster without GPUs. A cluster job checks its own node's device
# when it starts (subslope.devices.pick_device).
onstart:
    problems = []
    if workflow.remote_exec:
        pass
    elif workflow.executor_plugin.name == "slurm":
        problems = subslope.plan.slurm_gpu_problems(config)
    elif workflow.local_exec:
        problems = subslope.devices.device_problems(
            config, subslope.config.active_stages(config)
        )
    if problems:
        raise WorkflowError(
            "invalid configuration:\n  - " + "\n  - ".join(problems)
        )


RESOURCES = config["data"]["resources_dir"]
REGISTRY = subslope.io.resources.load_registry()


def resource_files(prefix):
    """Registered data files whose path starts with `prefix`, under RESOURCES."""
    return [
        f"{RESOURCES}/{entry.path}"
        for entry in REGISTRY
        if entry.path.startswith(prefix)
    ]


def data_inputs(prefix):
    """resource_files(prefix) as inputs of the rules that read them. Not ancient():
    with an ancient input whose fetch_data job runs, Snakemake leaves the readers' other
    reasons to rerun to the next invocation (snakemake/snakemake#4166), a stale result;
    a deleted data file is restored before the graph is built instead (above), so that
    it reruns no reader."""
    return resource_files(prefix)


# The real lenses the HST stages read (subslope.io.observation_set): the shipped 13 as
# fetched data, or the configured folder's catalogue, cutouts and manifest.
OBS_FOLDER, OBS_CATALOG, OBS_SHIPPED = subslope.io.observation_set.observation_folder(
    config
)


def observation_inputs():
    """Input files of the rules that read the real lenses."""
    if OBS_SHIPPED:
        return data_inputs("hst/")
    files = subslope.io.observation_set.observation_files(OBS_FOLDER, OBS_CATALOG)
    return [str(OBS_FOLDER / subslope.io.observation_set.MANIFEST), *map(str, files)]


def observation_source(files):
    """What the HST stages load (subslope.io.observations.load_hst), from the rule's
    observation_inputs(): the folder of the shipped lenses, else the configured
    catalogue file (its folder holds the cutouts)."""
    return os.path.dirname(files[0]) if OBS_SHIPPED else files[1]


def cosmos_files():
    """The registered files of the configured COSMOS folders (simulation.sources.folder),
    as data_inputs."""
    folder = config["simulation"]["sources"]["folder"]
    names = folder if isinstance(folder, list) else [folder]
    return [f for name in names for f in data_inputs(os.path.join(name, ""))]


def cosmos_dirs(files):
    """The COSMOS folders of `files`, in configured order."""
    return list(dict.fromkeys(os.path.dirname(f) for f in files))


# Simulation: one entry {scene, shard, multiplier, path} per shard file of the config.
SHARD_JOBS = subslope.plan.shard_jobs(config)
SIM_SCENES = sorted({job["scene"] for job in SHARD_JOBS})


def simulation_hash(scene):
    """Hash of the config values that determine the images of `scene`'s shards.

    The list of multipliers is left out: every multiplier's shards share their seed, so
    adding a multiplier leaves the existing CDM shards (and their profiles) valid and
    only the new multiplier is simulated and evaluated.
    """
    if scene not in _SIM_HASH:  # cached: the config is validated again for every call
        sections = subslope.simulation.resolve.simulation_sections(config, scene)
        sections.pop("multipliers", None)
        _SIM_HASH[scene] = subslope.config.config_hash(sections)
    return _SIM_HASH[scene]


_SIM_HASH = {}


def shard_job(wildcards):
    """The resolved configuration of one shard job, passed as a param (so a change reruns
    it); its stage flags are left out (a new stage reruns no shard)."""
    key = (wildcards.scene, wildcards.get("multiplier"))
    if key not in _SHARD_JOB:  # cached per scene and multiplier: the shards share it
        job = subslope.plan.shard_job_config(config, *key)
        _SHARD_JOB[key] = {k: v for k, v in job.items() if k != "stages"}
    return _SHARD_JOB[key]


_SHARD_JOB = {}


def shard_files(scene):
    """All shard files of `scene` (every multiplier for CDM scenes)."""
    return [job["path"] for job in SHARD_JOBS if job["scene"] == scene]


def domain_shards():
    """The first shards of domain.scene, as many as domain.n_images needs."""
    scene = config["domain"]["scene"]
    files = shard_files(scene)
    per_shard = config["simulation"]["scenes"][scene]["images_per_shard"]
    return files[: max(1, -(-config["domain"]["n_images"] // per_shard))]


def example_shard(scene):
    """The shard shown in the scene-example figure: shard 0 (a = 1 if simulated)."""
    jobs = [job for job in SHARD_JOBS if job["scene"] == scene and job["shard"] == 0]
    ones = [job for job in jobs if job["multiplier"] == 1.0]
    return (ones or jobs)[0]["path"]


STREAMING = subslope.config.STREAMED_SCENE in config["simulation"][
    "scenes"
] and subslope.config.STREAMED_SCENE not in subslope.config.shard_scenes(config)


def whitening_shards():
    """The shards the whitening statistics come from: the training shards, or the
    validation shards when the training images are streamed (training.data: stream)."""
    return shard_files("validation") if STREAMING else shard_files("train")


def stream_job():
    """The resolved configuration of the streamed scene (None unless training.data is
    stream): a change of it retrains, as a shard job's would resimulate."""
    if not STREAMING:
        return None
    job = subslope.plan.shard_job_config(config, subslope.config.STREAMED_SCENE)
    return {k: v for k, v in job.items() if k != "stages"}


def simulation_targets():
    """Shards, whitening statistics (if there are training shards) and scene figures
    (simulation.scene_examples)."""
    targets = [job["path"] for job in SHARD_JOBS]
    if whitening_shards():
        targets.append(rules.compute_whitening.output.json)
    if config["simulation"]["scene_examples"]:
        targets += expand(rules.plot_scene_examples.output.png, scene=SIM_SCENES)
    return targets


# ---------------------------------------------------------------------------------------
# Stages. A stage runs when its flag and the flags of every stage it needs are on
# (subslope.config.STAGE_NEEDS), so a switched-off stage never runs as a dependency.
STAGE_ON = subslope.config.active_stages(config)
for _name, _on in STAGE_ON.items():
    if config["stages"][_name] and not _on:
        logger.warning(
            f"stage {_name} is on but a stage it needs is off: it does not run"
        )


# ---------------------------------------------------------------------------------------
# Evaluation sets: which shards get profiles, and the calibration stack sizes.
CAL = config["calibration"]
CDM = config["cdm"]
CDM_SCENES = subslope.config.cdm_scenes(config)  # both grids' (t)NFW scenes
CONTROL_SCENES = [*CDM["field_controls"], *CDM["reference_controls"]]
ABUNDANCE_SCENES = list(CDM["abundance"])
RUN = config["run_name"]
CAL_N = sorted(CAL["n_images"])
GRID = config["inference"]["gamma_grid"]


def eval_scenes():
    """Scenes whose shards are evaluated: the calibration, CDM and null-test scenes."""
    scenes = [
        CAL["single_scene"],
        CAL["stack_scene"],
        *CDM_SCENES,
        *(CONTROL_SCENES + ABUNDANCE_SCENES if STAGE_ON["cdm_grid"] else []),
        *(config["null_tests"]["scenes"] if STAGE_ON["null_tests"] else []),
    ]
    simulated = {job["scene"] for job in SHARD_JOBS}
    return [s for s in dict.fromkeys(scenes) if s in simulated]


def shard_priority(wildcards):
    """Scheduling priority of a shard job: 1 for the training and validation shards
    (training needs them all before it starts), 0 for the others."""
    return 1 if wildcards.scene in ("train", "validation") else 0


def profile_path(job):
    """Profiles file of one shard job (mirrors the shard path)."""
    return job["path"].replace(
        "results/simulate_shard/", "results/evaluate_profiles/", 1
    )


def profile_files(scene, multiplier=None):
    """Profiles files of every shard of `scene` (of one multiplier for CDM scenes)."""
    return [
        profile_path(job)
        for job in SHARD_JOBS
        if job["scene"] == scene
        and (multiplier is None or job["multiplier"] == multiplier)
    ]


def calibration_inputs(wildcards):
    """N = 1: single images of calibration.single_scene; N > 1: sets of stack_scene."""
    scene = CAL["single_scene"] if int(wildcards.n) == 1 else CAL["stack_scene"]
    return profile_files(scene)


def cdm_inputs():
    return [profile_path(job) for job in SHARD_JOBS if job["scene"] in CDM_SCENES]


def derived_seed(section):
    """The section's seed, or one derived from the global seed when it is null."""
    value = config[section].get("seed")
    return (
        subslope.plan.derived_seed(config["seed"], section)
        if value is None
        else int(value)
    )


# Signal budget: shard 0 of every scene but validation, one table each.
def budget_jobs():
    """The shard-0 jobs of every simulated scene but validation (each multiplier apart)."""
    return [
        job for job in SHARD_JOBS if job["shard"] == 0 and job["scene"] != "validation"
    ]


def contrast_groups():
    """[scene, a_low, a_high, shard at a_low, shard at a_high] of shard 0 of every CDM
    scene simulated at both multipliers of signal_budget.contrast (rule
    concentration_contrast)."""
    pair = config["signal_budget"]["contrast"]
    if not pair:
        return []
    groups = []
    for scene in CDM_SCENES:
        at = {
            float(job["multiplier"]): job["path"]
            for job in SHARD_JOBS
            if job["scene"] == scene and job["shard"] == 0
        }
        low, high = (float(a) for a in pair)
        if low in at and high in at:
            groups.append([scene, low, high, at[low], at[high]])
    return groups


def budget_path(job):
    """The signal-budget table of one shard job (mirrors the shard path)."""
    return (
        job["path"]
        .replace("results/simulate_shard/", "results/signal_budget/", 1)
        .replace(".h5", ".csv")
    )


def benchmark_files():
    """Benchmark TSVs of every job of the stages that run, grouped by stage."""
    out = {}
    if STAGE_ON["simulate"]:
        out["simulate"] = [
            job["path"]
            .replace("results/simulate_shard/", "results/benchmarks/simulate_shard/")
            .replace(".h5", ".tsv")
            for job in SHARD_JOBS
        ]
        if whitening_shards():
            out["simulate"].append("results/benchmarks/compute_whitening.tsv")
    if STAGE_ON["domain"]:
        out["domain"] = [
            "results/benchmarks/fit_lens_light.tsv",
            "results/benchmarks/check_domain.tsv",
        ]
    if STAGE_ON["train"]:
        out["train"] = ["results/benchmarks/train_estimator.tsv"]
    if STAGE_ON["evaluate"]:
        out["evaluate"] = [
            profile_path(job)
            .replace(
                "results/evaluate_profiles/", "results/benchmarks/evaluate_profiles/"
            )
            .replace(".h5", ".tsv")
            for job in SHARD_JOBS
            if job["scene"] in eval_scenes()
        ]
    if STAGE_ON["calibrate"]:
        out["calibrate"] = [
            f"results/benchmarks/calibrate_threshold/N{n}.tsv" for n in CAL_N
        ]
        out["calibrate"].append("results/benchmarks/summarize_coverage.tsv")
    if STAGE_ON["cdm_grid"]:
        out["cdm_grid"] = [
            "results/benchmarks/effective_slope.tsv",
            "results/benchmarks/measure_cdm_grid.tsv",
        ] + (["results/benchmarks/measure_epl_control.tsv"] if CONTROL_SCENES else [])
        if ABUNDANCE_SCENES:
            out["cdm_grid"].append("results/benchmarks/measure_abundance.tsv")
    if STAGE_ON["signal_budget"]:
        out["signal_budget"] = [
            budget_path(job)
            .replace("results/signal_budget/", "results/benchmarks/signal_budget/")
            .replace(".csv", ".tsv")
            for job in budget_jobs()
        ] + ["results/benchmarks/summarize_signal_budget.tsv"]
        if contrast_groups():
            out["signal_budget"].append("results/benchmarks/concentration_contrast.tsv")
    if null_tests_on():
        out["null_tests"] = ["results/benchmarks/null_tests.tsv"]
    if halo_free_on():
        out.setdefault("null_tests", []).extend(
            f"results/benchmarks/halo_free_profiles/{job['scene']}/shard_{job['shard']}.tsv"
            for job in HALO_FREE_JOBS
        )
        out["null_tests"].append("results/benchmarks/halo_free_null.tsv")
    if visibility_on():
        out.setdefault("null_tests", []).extend(
            subhalo_free_path(job)
            .replace("results/null_tests/", "results/benchmarks/", 1)
            .replace(".h5", ".tsv")
            for job in VISIBILITY_JOBS
        )
        out["null_tests"].append("results/benchmarks/cdm_visibility.tsv")
    if STAGE_ON["hst"]:
        out["hst"] = ["results/benchmarks/analyze_hst.tsv"]
    if STAGE_ON["figures"]:
        out["figures"] = ["results/benchmarks/plot_training_curves.tsv"]
        if STAGE_ON["calibrate"]:
            out["figures"].append("results/benchmarks/plot_validation.tsv")
    return out


def all_targets():
    """Final outputs of the stages switched on in config['stages']."""
    targets = resource_files("")
    if STAGE_ON["gallery"]:
        targets += rules.plot_hst_gallery.output
    if STAGE_ON["simulate"]:
        targets += simulation_targets()
    if STAGE_ON["domain"]:
        targets += rules.fit_lens_light.output + rules.check_domain.output
    if STAGE_ON["train"]:
        targets += rules.train_estimator.output
    if STAGE_ON["evaluate"]:
        targets += [
            profile_path(job) for job in SHARD_JOBS if job["scene"] in eval_scenes()
        ]
    if STAGE_ON["calibrate"]:
        targets += rules.summarize_coverage.output
    if STAGE_ON["cdm_grid"]:
        targets += rules.measure_cdm_grid.output
    if null_tests_on():
        targets += rules.null_tests.output
    if halo_free_on():
        targets += rules.halo_free_null.output
    if visibility_on():
        targets += rules.cdm_visibility.output
    if STAGE_ON["hst"]:
        targets += rules.analyze_hst.output
    if STAGE_ON["signal_budget"]:
        targets += rules.summarize_signal_budget.output
    if STAGE_ON["figures"]:
        targets += rules.plot_training_curves.output
        if STAGE_ON["calibrate"]:
            targets += rules.plot_validation.output
    if STAGE_ON["summary"]:
        targets += rules.write_summary.output
    return targets


# ---------------------------------------------------------------------------------------
# Summary: its inputs are the results of the stages that run (missing ones are reported
# as "not run"); its CSVs sit beside results/summary.md.
SUMMARY_CSVS = [
    "hst_result",
    "cdm_prediction",
    "coverage",
    "null_tests",
    "halo_free",
    "nsub_bias",
    "cdm_visibility",
    "trend",
    "stage_runtime",
    "response",
]
# Hash of the whole validated config except the data location (machine-specific).
CONFIG_HASH = subslope.config.config_hash(
    {k: v for k, v in config.items() if k != "data"}
)[:16]
CONFIG_FILES = [os.path.relpath(f) for f in _CONFIG_FILES]


def null_tests_on():
    """The null_tests stage runs and has scenes to test."""
    return STAGE_ON["null_tests"] and bool(config["null_tests"]["scenes"])


# The halo-free null test's shards (rules halo_free_profiles, halo_free_null).
HALO_FREE_N = subslope.config.halo_free_shards(config) if STAGE_ON["null_tests"] else 0
HALO_FREE_JOBS = [
    job
    for job in SHARD_JOBS
    if job["scene"] == CAL["stack_scene"] and job["shard"] < HALO_FREE_N
]
HALO_FREE_VARIANTS = ("sheets_kept", "sheets_removed")


def halo_free_files(variant):
    return [
        f"results/null_tests/halo_free/{variant}/{job['scene']}/shard_{job['shard']}.h5"
        for job in HALO_FREE_JOBS
    ]


def halo_free_on():
    """The halo-free null test runs (null_tests.halo_free_sets > 0)."""
    return STAGE_ON["null_tests"] and HALO_FREE_N > 0


# The CDM visibility check's shards: the shards of every CDM scene at every multiplier (rules
# subhalo_free_profiles, cdm_visibility).
VISIBILITY_JOBS = [
    job
    for job in SHARD_JOBS
    if STAGE_ON["null_tests"]
    and STAGE_ON["cdm_grid"]
    and config["null_tests"]["cdm_visibility"]
    and job["scene"] in CDM_SCENES
]


def subhalo_free_path(job):
    """Profiles file of one CDM shard re-rendered without its subhalos."""
    return job["path"].replace(
        "results/simulate_shard/", "results/null_tests/subhalo_free/", 1
    )


def visibility_on():
    """The CDM visibility check runs."""
    return bool(VISIBILITY_JOBS)


def field_subhalo_free():
    """{shard index: the a = 1 subhalo-free re-render of the field grid's NFW shard}: the
    common-draws sets without subhalos that controls and abundance scenes pair with."""
    return {
        job["shard"]: subhalo_free_path(job)
        for job in VISIBILITY_JOBS
        if job["scene"] == CDM["nfw_scene"] and float(job["multiplier"]) == 1.0
    }


def abundance_groups():
    """[scene, profile, N_max, profiles files, subhalo-free profiles files] of every scene
    of cdm.abundance at a = 1 (rule measure_abundance)."""
    free = field_subhalo_free()
    groups = []
    for scene in ABUNDANCE_SCENES:
        sc, _ = subslope.simulation.resolve.resolved_scene(config, scene)
        jobs = [
            job
            for job in SHARD_JOBS
            if job["scene"] == scene and float(job["multiplier"]) == 1.0
        ]
        removed = [free[job["shard"]] for job in jobs if job["shard"] in free]
        groups.append(
            [
                scene,
                sc.subhalos.profile,
                int(sc.subhalos.count.support[1]),
                [profile_path(job) for job in jobs],
                removed if len(removed) == len(jobs) else [],
            ]
        )
    return groups


def control_groups():
    """[grid, scene, gamma, profiles files, subhalo-free profiles files] of every matched
    EPL control, read by rule measure_epl_control. Each control shard pairs with the a = 1
    subhalo-free re-render of its grid's NFW shard of the same index (none without the
    visibility check)."""
    groups = []
    for grid, (nfw, _) in subslope.config.cdm_grids(config).items():
        for scene in CDM[f"{grid}_controls"]:
            sc, _ = subslope.simulation.resolve.resolved_scene(config, scene)
            jobs = [job for job in SHARD_JOBS if job["scene"] == scene]
            free = {
                job["shard"]: subhalo_free_path(job)
                for job in VISIBILITY_JOBS
                if job["scene"] == nfw and float(job["multiplier"]) == 1.0
            }
            removed = [free[job["shard"]] for job in jobs if job["shard"] in free]
            groups.append(
                [
                    grid,
                    scene,
                    sc.subhalos.fixed_gamma,
                    [profile_path(job) for job in jobs],
                    removed if len(removed) == len(jobs) else [],
                ]
            )
    return groups


# The records of studies/concentration_classifier.py (run by hand; no rule makes them).
CLASSIFIER_DIR = "results/studies/concentration_classifier"

# The table of trainings that `subslope seeds` writes (subslope.campaigns.seeds.SEEDS_CSV).
SEEDS_CSV = "results/seeds/seeds.csv"


def summary_inputs(wildcards):
    inputs = {}
    if null_tests_on():
        inputs["null_tests"] = rules.null_tests.output.csv
    if visibility_on():
        inputs["cdm_visibility"] = rules.cdm_visibility.output.csv
    if halo_free_on():
        inputs["halo_free"] = rules.halo_free_null.output.csv
        inputs["nsub_bias"] = rules.halo_free_null.output.bias
    if STAGE_ON["train"]:
        inputs["training_log"] = rules.train_estimator.output.log_csv
    if STAGE_ON["hst"]:
        inputs["hst"] = rules.analyze_hst.output.csv
        inputs["leave_one_out"] = rules.analyze_hst.output.loo
    if STAGE_ON["domain"]:
        inputs["domain"] = rules.check_domain.output.csv
    if STAGE_ON["cdm_grid"]:
        inputs["cdm"] = rules.measure_cdm_grid.output.csv
        if CONTROL_SCENES:
            inputs["epl_control"] = rules.measure_epl_control.output.csv
        if ABUNDANCE_SCENES:
            inputs["abundance"] = rules.measure_abundance.output.csv
    if STAGE_ON["calibrate"]:
        inputs["calibration"] = rules.summarize_coverage.output.csv
        inputs["trend"] = rules.plot_validation.output.trend
    if STAGE_ON["signal_budget"]:
        inputs["signal_budget"] = rules.summarize_signal_budget.output.csv
        if contrast_groups():
            inputs["contrast"] = rules.concentration_contrast.output.csv
    classifier = sorted(glob.glob(f"{CLASSIFIER_DIR}/*.json"))
    if STAGE_ON["cdm_grid"] and classifier:
        # studies/concentration_classifier.py writes them
        inputs["classifier"] = classifier
    if STAGE_ON["hst"] and os.path.exists(SEEDS_CSV):
        inputs["seeds"] = SEEDS_CSV  # `subslope seeds` writes it; no rule makes it
    return inputs
