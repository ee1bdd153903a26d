"""The workflow's files: which shards, profiles, tables and benchmark records each rule
of ``workflow/rules`` reads and writes, computed once from the validated config.

``workflow/rules/common.smk`` builds one :class:`Targets` when the workflow loads and
binds its :data:`HELPERS` (input functions and paths) and :data:`CONSTANTS` (the
campaign's plan) to the names the rule files use; the functions that name other rules'
outputs take the workflow's ``rules`` object.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Mapping
from typing import Any

from subslope import config as _config
from subslope.campaigns.seeds import SEEDS_CSV
from subslope.io import observation_set
from subslope.io.resources import load_registry
from subslope.plan import derived_seed as _derived_seed
from subslope.plan import shard_job_config, shard_jobs
from subslope.simulation.resolve import resolved_scene, simulation_sections

__all__ = ["Targets", "HELPERS", "CONSTANTS", "SUMMARY_CSVS", "CLASSIFIER_DIR", "SEEDS_CSV"]

#: The CSVs beside ``results/summary.md``.
SUMMARY_CSVS = (
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
)
#: The records of ``studies/concentration_classifier.py`` (run by hand; no rule makes them).
CLASSIFIER_DIR = "results/studies/concentration_classifier"
#: Methods of :class:`Targets` the rule files call by name.
HELPERS = (
    "resource_files", "data_inputs", "observation_inputs", "observation_source",
    "cosmos_files", "cosmos_dirs", "simulation_hash", "shard_job", "shard_files",
    "domain_shards", "example_shard", "whitening_shards", "stream_job", "eval_scenes",
    "shard_priority", "profile_path", "profile_files", "calibration_inputs", "cdm_inputs",
    "derived_seed", "budget_jobs", "contrast_groups", "budget_path", "null_tests_on",
    "halo_free_files", "halo_free_on", "subhalo_free_path", "visibility_on",
    "abundance_groups", "control_groups",
)  # fmt: skip
#: Attributes of :class:`Targets` the rule files read as upper-case names.
CONSTANTS = (
    "RESOURCES", "REGISTRY", "OBS_FOLDER", "OBS_CATALOG", "OBS_SHIPPED", "SHARD_JOBS",
    "SIM_SCENES", "STREAMING", "STAGE_ON", "CAL", "CDM", "CDM_SCENES", "CONTROL_SCENES",
    "ABUNDANCE_SCENES", "RUN", "CAL_N", "GRID", "HALO_FREE_N", "HALO_FREE_JOBS",
    "HALO_FREE_VARIANTS", "VISIBILITY_JOBS", "CONFIG_HASH",
)  # fmt: skip


def _without_stages(job: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in job.items() if k != "stages"}


class Targets:
    """The plan of one campaign (a validated ``config``) as the workflow's files."""

    HALO_FREE_VARIANTS = ("sheets_kept", "sheets_removed")

    def __init__(self, config: Mapping[str, Any]):
        self.config = config
        self.RESOURCES = config["data"]["resources_dir"]
        self.REGISTRY = load_registry()
        # the real lenses: the shipped 13 as fetched data, or the configured folder's
        self.OBS_FOLDER, self.OBS_CATALOG, self.OBS_SHIPPED = observation_set.observation_folder(
            config
        )
        self.SHARD_JOBS = shard_jobs(config)
        self.SIM_SCENES = sorted({job["scene"] for job in self.SHARD_JOBS})
        scenes, streamed = config["simulation"]["scenes"], _config.STREAMED_SCENE
        self.STREAMING = streamed in scenes and streamed not in _config.shard_scenes(config)
        self.STAGE_ON = _config.active_stages(config)
        self.CAL, self.CDM = config["calibration"], config["cdm"]
        self.CDM_SCENES = _config.cdm_scenes(config)  # both grids' (t)NFW scenes
        self.CONTROL_SCENES = [*self.CDM["field_controls"], *self.CDM["reference_controls"]]
        self.ABUNDANCE_SCENES = list(self.CDM["abundance"])
        self.RUN = config["run_name"]
        self.CAL_N = sorted(self.CAL["n_images"])
        self.GRID = config["inference"]["gamma_grid"]
        null_tests = self.STAGE_ON["null_tests"]
        self.HALO_FREE_N = _config.halo_free_shards(config) if null_tests else 0
        self.HALO_FREE_JOBS = [
            job
            for job in self.SHARD_JOBS
            if job["scene"] == self.CAL["stack_scene"] and job["shard"] < self.HALO_FREE_N
        ]
        visibility = null_tests and self.STAGE_ON["cdm_grid"]
        self.VISIBILITY_JOBS = [
            job
            for job in self.SHARD_JOBS
            if visibility and config["null_tests"]["cdm_visibility"]
            and job["scene"] in self.CDM_SCENES
        ]  # fmt: skip
        # the whole validated config but the data location (machine-specific)
        self.CONFIG_HASH = _config.config_hash({k: v for k, v in config.items() if k != "data"})[
            :16
        ]
        self._sim_hash: dict[str, str] = {}
        self._shard_job: dict[tuple, dict[str, Any]] = {}

    # ------------------------------------------------------------------------ data
    def resource_files(self, prefix: str) -> list[str]:
        """Registered data files whose path starts with ``prefix``, under RESOURCES."""
        return [
            f"{self.RESOURCES}/{entry.path}"
            for entry in self.REGISTRY
            if entry.path.startswith(prefix)
        ]

    def data_inputs(self, prefix: str) -> list[str]:
        """:meth:`resource_files` as inputs of the rules that read them. Not ancient():
        with an ancient input whose fetch_data job runs, Snakemake leaves the readers'
        other reasons to rerun to the next invocation (snakemake/snakemake#4166), a stale
        result; a deleted data file is restored before the graph is built instead
        (common.smk), so that it reruns no reader."""
        return self.resource_files(prefix)

    def observation_inputs(self) -> list[str]:
        """Input files of the rules that read the real lenses."""
        if self.OBS_SHIPPED:
            return self.data_inputs("hst/")
        files = observation_set.observation_files(self.OBS_FOLDER, self.OBS_CATALOG)
        return [str(self.OBS_FOLDER / observation_set.MANIFEST), *map(str, files)]

    def observation_source(self, files) -> str:
        """What the HST stages load (:func:`subslope.io.observations.load_hst`), from the
        rule's :meth:`observation_inputs`: the folder of the shipped lenses, else the
        configured catalogue file (its folder holds the cutouts)."""
        return os.path.dirname(files[0]) if self.OBS_SHIPPED else files[1]

    def cosmos_files(self) -> list[str]:
        """The registered files of the configured COSMOS folders
        (``simulation.sources.folder``), as :meth:`data_inputs`."""
        folder = self.config["simulation"]["sources"]["folder"]
        names = folder if isinstance(folder, list) else [folder]
        return [f for name in names for f in self.data_inputs(os.path.join(name, ""))]

    @staticmethod
    def cosmos_dirs(files) -> list[str]:
        """The COSMOS folders of ``files``, in configured order."""
        return list(dict.fromkeys(os.path.dirname(f) for f in files))

    # ------------------------------------------------------------------ simulation
    def simulation_hash(self, scene: str) -> str:
        """Hash of the config values that determine the images of ``scene``'s shards.

        The list of multipliers is left out: every multiplier's shards share their seed,
        so adding a multiplier leaves the existing CDM shards (and their profiles) valid
        and only the new multiplier is simulated and evaluated."""
        if scene not in self._sim_hash:
            sections = simulation_sections(self.config, scene)
            sections.pop("multipliers", None)
            self._sim_hash[scene] = _config.config_hash(sections)
        return self._sim_hash[scene]

    def shard_job(self, wildcards) -> dict[str, Any]:
        """The resolved configuration of one shard job, passed as a param (so a change
        reruns it); its stage flags are left out (a new stage reruns no shard)."""
        key = (wildcards.scene, wildcards.get("multiplier"))
        if key not in self._shard_job:  # the shards of a scene and multiplier share it
            self._shard_job[key] = _without_stages(shard_job_config(self.config, *key))
        return self._shard_job[key]

    def shard_files(self, scene: str) -> list[str]:
        """All shard files of ``scene`` (every multiplier for CDM scenes)."""
        return [job["path"] for job in self.SHARD_JOBS if job["scene"] == scene]

    def domain_shards(self) -> list[str]:
        """The first shards of domain.scene, as many as domain.n_images needs."""
        scene = self.config["domain"]["scene"]
        per_shard = self.config["simulation"]["scenes"][scene]["images_per_shard"]
        return self.shard_files(scene)[: max(1, -(-self.config["domain"]["n_images"] // per_shard))]

    def example_shard(self, scene: str) -> str:
        """The shard shown in the scene-example figure: shard 0 (a = 1 if simulated)."""
        jobs = [job for job in self.SHARD_JOBS if job["scene"] == scene and job["shard"] == 0]
        ones = [job for job in jobs if job["multiplier"] == 1.0]
        return (ones or jobs)[0]["path"]

    def whitening_shards(self) -> list[str]:
        """The shards the whitening statistics come from: the training shards, or the
        validation shards when the training images are streamed."""
        return self.shard_files("validation" if self.STREAMING else "train")

    def stream_job(self) -> dict[str, Any] | None:
        """The resolved configuration of the streamed scene (None unless training.data is
        stream): a change of it retrains, as a shard job's would resimulate."""
        if not self.STREAMING:
            return None
        return _without_stages(shard_job_config(self.config, _config.STREAMED_SCENE))

    @staticmethod
    def shard_priority(wildcards) -> int:
        """Scheduling priority of a shard job: 1 for the training and validation shards
        (training needs them all before it starts), 0 for the others."""
        return 1 if wildcards.scene in ("train", "validation") else 0

    # ------------------------------------------------------------------ evaluation
    def eval_scenes(self) -> list[str]:
        """Scenes whose shards are evaluated: the calibration, CDM and null-test scenes."""
        on = self.STAGE_ON
        scenes = [
            self.CAL["single_scene"],
            self.CAL["stack_scene"],
            *self.CDM_SCENES,
            *(self.CONTROL_SCENES + self.ABUNDANCE_SCENES if on["cdm_grid"] else []),
            *(self.config["null_tests"]["scenes"] if on["null_tests"] else []),
        ]
        simulated = {job["scene"] for job in self.SHARD_JOBS}
        return [s for s in dict.fromkeys(scenes) if s in simulated]

    @staticmethod
    def profile_path(job: Mapping[str, Any]) -> str:
        """Profiles file of one shard job (mirrors the shard path)."""
        return job["path"].replace("results/simulate_shard/", "results/evaluate_profiles/", 1)

    def profile_files(self, scene: str, multiplier=None) -> list[str]:
        """Profiles files of every shard of ``scene`` (of one multiplier for CDM scenes)."""
        return [
            self.profile_path(job)
            for job in self.SHARD_JOBS
            if job["scene"] == scene and (multiplier is None or job["multiplier"] == multiplier)
        ]

    def calibration_inputs(self, wildcards) -> list[str]:
        """N = 1: single images of calibration.single_scene; N > 1: sets of stack_scene."""
        single = int(wildcards.n) == 1
        return self.profile_files(self.CAL["single_scene" if single else "stack_scene"])

    def cdm_inputs(self) -> list[str]:
        return [self.profile_path(j) for j in self.SHARD_JOBS if j["scene"] in self.CDM_SCENES]

    def derived_seed(self, section: str) -> int:
        """The section's seed, or one derived from the global seed when it is null."""
        value = self.config[section].get("seed")
        return _derived_seed(self.config["seed"], section) if value is None else int(value)

    # --------------------------------------------------------------- signal budget
    def budget_jobs(self) -> list[dict[str, Any]]:
        """The shard-0 jobs of every simulated scene but validation (each multiplier
        apart)."""
        return [j for j in self.SHARD_JOBS if j["shard"] == 0 and j["scene"] != "validation"]

    def contrast_groups(self) -> list[list]:
        """[scene, a_low, a_high, shard at a_low, shard at a_high] of shard 0 of every CDM
        scene simulated at both multipliers of signal_budget.contrast (rule
        concentration_contrast)."""
        pair = self.config["signal_budget"]["contrast"]
        if not pair:
            return []
        low, high = (float(a) for a in pair)
        groups = []
        for scene in self.CDM_SCENES:
            at = {
                float(job["multiplier"]): job["path"]
                for job in self.SHARD_JOBS
                if job["scene"] == scene and job["shard"] == 0
            }
            if low in at and high in at:
                groups.append([scene, low, high, at[low], at[high]])
        return groups

    @staticmethod
    def budget_path(job: Mapping[str, Any]) -> str:
        """The signal-budget table of one shard job (mirrors the shard path)."""
        path = job["path"].replace("results/simulate_shard/", "results/signal_budget/", 1)
        return path.replace(".h5", ".csv")

    # ------------------------------------------------------------------ null tests
    def null_tests_on(self) -> bool:
        """The null_tests stage runs and has scenes to test."""
        return self.STAGE_ON["null_tests"] and bool(self.config["null_tests"]["scenes"])

    def halo_free_files(self, variant: str) -> list[str]:
        return [
            f"results/null_tests/halo_free/{variant}/{job['scene']}/shard_{job['shard']}.h5"
            for job in self.HALO_FREE_JOBS
        ]

    def halo_free_on(self) -> bool:
        """The halo-free null test runs (null_tests.halo_free_sets > 0)."""
        return self.STAGE_ON["null_tests"] and self.HALO_FREE_N > 0

    @staticmethod
    def subhalo_free_path(job: Mapping[str, Any]) -> str:
        """Profiles file of one CDM shard re-rendered without its subhalos."""
        return job["path"].replace("results/simulate_shard/", "results/null_tests/subhalo_free/", 1)

    def visibility_on(self) -> bool:
        """The CDM visibility check runs."""
        return bool(self.VISIBILITY_JOBS)

    def _subhalo_free_of(self, scene: str) -> dict[int, str]:
        """{shard index: the a = 1 subhalo-free re-render of ``scene``'s shard}: the
        common-draws sets without subhalos that controls and abundance scenes pair with."""
        return {
            job["shard"]: self.subhalo_free_path(job)
            for job in self.VISIBILITY_JOBS
            if job["scene"] == scene and float(job["multiplier"]) == 1.0
        }

    def _paired(self, scene: str, free: Mapping[int, str]) -> tuple[list[str], list[str]]:
        """Profiles files of ``scene`` at a = 1 and their subhalo-free pairs (none unless
        every shard has one)."""
        jobs = [
            j for j in self.SHARD_JOBS if j["scene"] == scene and j["multiplier"] in (None, 1.0)
        ]
        removed = [free[job["shard"]] for job in jobs if job["shard"] in free]
        return [self.profile_path(j) for j in jobs], removed if len(removed) == len(jobs) else []

    def abundance_groups(self) -> list[list]:
        """[scene, profile, N_max, profiles files, subhalo-free profiles files] of every
        scene of cdm.abundance at a = 1 (rule measure_abundance)."""
        free = self._subhalo_free_of(self.CDM["nfw_scene"])
        groups = []
        for scene in self.ABUNDANCE_SCENES:
            sc, _ = resolved_scene(self.config, scene)
            files, removed = self._paired(scene, free)
            groups.append(
                [scene, sc.subhalos.profile, int(sc.subhalos.count.support[1]), files, removed]
            )
        return groups

    def control_groups(self) -> list[list]:
        """[grid, scene, gamma, profiles files, subhalo-free profiles files] of every
        matched EPL control (rule measure_epl_control). Each control shard pairs with the
        a = 1 subhalo-free re-render of its grid's NFW shard of the same index (none
        without the visibility check)."""
        groups = []
        for grid, (nfw, _) in _config.cdm_grids(self.config).items():
            free = self._subhalo_free_of(nfw)
            for scene in self.CDM[f"{grid}_controls"]:
                sc, _ = resolved_scene(self.config, scene)
                files, removed = self._paired(scene, free)
                groups.append([grid, scene, sc.subhalos.fixed_gamma, files, removed])
        return groups

    # -------------------------------------------------------------------- outputs
    def benchmark_files(self) -> dict[str, list[str]]:
        """Benchmark TSVs of every job of the stages that run, grouped by stage."""
        on, out = self.STAGE_ON, {}

        def moved(path: str, src: str, dst: str, ext: str = ".h5") -> str:
            return path.replace(src, dst, 1).replace(ext, ".tsv")

        sim, bench = "results/simulate_shard/", "results/benchmarks/"
        if on["simulate"]:
            out["simulate"] = [
                moved(j["path"], sim, f"{bench}simulate_shard/") for j in self.SHARD_JOBS
            ]
            if self.whitening_shards():
                out["simulate"].append(f"{bench}compute_whitening.tsv")
        if on["domain"]:
            out["domain"] = [f"{bench}fit_lens_light.tsv", f"{bench}check_domain.tsv"]
        if on["train"]:
            out["train"] = [f"{bench}train_estimator.tsv"]
        if on["evaluate"]:
            scenes = self.eval_scenes()
            out["evaluate"] = [
                moved(j["path"], sim, f"{bench}evaluate_profiles/")
                for j in self.SHARD_JOBS
                if j["scene"] in scenes
            ]
        if on["calibrate"]:
            out["calibrate"] = [f"{bench}calibrate_threshold/N{n}.tsv" for n in self.CAL_N]
            out["calibrate"].append(f"{bench}summarize_coverage.tsv")
        if on["cdm_grid"]:
            out["cdm_grid"] = [f"{bench}effective_slope.tsv", f"{bench}measure_cdm_grid.tsv"]
            if self.CONTROL_SCENES:
                out["cdm_grid"].append(f"{bench}measure_epl_control.tsv")
            if self.ABUNDANCE_SCENES:
                out["cdm_grid"].append(f"{bench}measure_abundance.tsv")
        if on["signal_budget"]:
            out["signal_budget"] = [
                moved(
                    self.budget_path(j), "results/signal_budget/", f"{bench}signal_budget/", ".csv"
                )
                for j in self.budget_jobs()
            ] + [f"{bench}summarize_signal_budget.tsv"]
            if self.contrast_groups():
                out["signal_budget"].append(f"{bench}concentration_contrast.tsv")
        out.update(self._null_test_benchmarks(bench))
        if on["hst"]:
            out["hst"] = [f"{bench}analyze_hst.tsv"]
        if on["figures"]:
            out["figures"] = [f"{bench}plot_training_curves.tsv"]
            if on["calibrate"]:
                out["figures"].append(f"{bench}plot_validation.tsv")
        return out

    def _null_test_benchmarks(self, bench: str) -> dict[str, list[str]]:
        files = [f"{bench}null_tests.tsv"] if self.null_tests_on() else []
        if self.halo_free_on():
            files += [
                f"{bench}halo_free_profiles/{job['scene']}/shard_{job['shard']}.tsv"
                for job in self.HALO_FREE_JOBS
            ] + [f"{bench}halo_free_null.tsv"]
        if self.visibility_on():
            files += [
                self.subhalo_free_path(job)
                .replace("results/null_tests/", bench, 1)
                .replace(".h5", ".tsv")
                for job in self.VISIBILITY_JOBS
            ] + [f"{bench}cdm_visibility.tsv"]
        return {"null_tests": files} if files else {}

    def simulation_targets(self, rules, expand) -> list[str]:
        """Shards, whitening statistics (if there are training shards) and scene figures
        (simulation.scene_examples)."""
        targets = [job["path"] for job in self.SHARD_JOBS]
        if self.whitening_shards():
            targets.append(rules.compute_whitening.output.json)
        if self.config["simulation"]["scene_examples"]:
            targets += expand(rules.plot_scene_examples.output.png, scene=self.SIM_SCENES)
        return targets

    def all_targets(self, rules, expand) -> list[str]:
        """Final outputs of the stages switched on in ``config['stages']``."""
        on, targets = self.STAGE_ON, self.resource_files("")

        def outputs(*names: str) -> None:
            for name in names:
                targets.extend(getattr(rules, name).output)

        if on["gallery"]:
            outputs("plot_hst_gallery")
        if on["simulate"]:
            targets.extend(self.simulation_targets(rules, expand))
        if on["domain"]:
            outputs("fit_lens_light", "check_domain")
        if on["train"]:
            outputs("train_estimator")
        if on["evaluate"]:
            scenes = self.eval_scenes()
            targets.extend(self.profile_path(j) for j in self.SHARD_JOBS if j["scene"] in scenes)
        for runs, name in (
            (on["calibrate"], "summarize_coverage"),
            (on["cdm_grid"], "measure_cdm_grid"),
            (self.null_tests_on(), "null_tests"),
            (self.halo_free_on(), "halo_free_null"),
            (self.visibility_on(), "cdm_visibility"),
            (on["hst"], "analyze_hst"),
            (on["signal_budget"], "summarize_signal_budget"),
            (on["figures"], "plot_training_curves"),
            (on["figures"] and on["calibrate"], "plot_validation"),
            (on["summary"], "write_summary"),
        ):
            if runs:
                outputs(name)
        return targets

    def summary_inputs(self, rules) -> dict[str, Any]:
        """The results the summary reads, of the stages that run (missing ones are
        reported as "not run")."""
        on, r, inputs = self.STAGE_ON, rules, {}
        if self.null_tests_on():
            inputs["null_tests"] = r.null_tests.output.csv
        if self.visibility_on():
            inputs["cdm_visibility"] = r.cdm_visibility.output.csv
        if self.halo_free_on():
            inputs["halo_free"] = r.halo_free_null.output.csv
            inputs["nsub_bias"] = r.halo_free_null.output.bias
        if on["train"]:
            inputs["training_log"] = r.train_estimator.output.log_csv
        if on["hst"]:
            inputs["hst"], inputs["leave_one_out"] = (
                r.analyze_hst.output.csv,
                r.analyze_hst.output.loo,
            )
        if on["domain"]:
            inputs["domain"] = r.check_domain.output.csv
        if on["cdm_grid"]:
            inputs["cdm"] = r.measure_cdm_grid.output.csv
            if self.CONTROL_SCENES:
                inputs["epl_control"] = r.measure_epl_control.output.csv
            if self.ABUNDANCE_SCENES:
                inputs["abundance"] = r.measure_abundance.output.csv
        if on["calibrate"]:
            inputs["calibration"] = r.summarize_coverage.output.csv
            inputs["trend"] = r.plot_validation.output.trend
        if on["signal_budget"]:
            inputs["signal_budget"] = r.summarize_signal_budget.output.csv
            if self.contrast_groups():
                inputs["contrast"] = r.concentration_contrast.output.csv
        classifier = sorted(glob.glob(f"{CLASSIFIER_DIR}/*.json"))
        if on["cdm_grid"] and classifier:
            inputs["classifier"] = classifier  # studies/concentration_classifier.py writes them
        if on["hst"] and os.path.exists(SEEDS_CSV):
            inputs["seeds"] = SEEDS_CSV  # `subslope seeds` writes it; no rule makes it
        return inputs
