"""Planning of the workflow: which shard jobs a config asks for, their paths, the
seeds derived for the later stages, and how many cluster jobs a dry run's jobs make
(:func:`count_cluster_jobs`). Pure Python and numpy (no torch, h5py or plotting), so
``snakemake -n`` stays fast.
"""

from __future__ import annotations

import copy
import hashlib
import os
import re
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from subslope import config as _config
from subslope.config import RUN_ONLY_RENDER_KEYS
from subslope.simulation.resolve import resolved_scene, scene_multipliers

__all__ = [
    "runnable_config",
    "SHARD_DIR",
    "cache_folder_problems",
    "RUN_ONLY_RENDER_KEYS",
    "count_cluster_jobs",
    "derived_seed",
    "host_rules",
    "plan_problems",
    "plan_warnings",
    "project_root",
    "theta_e_warnings",
    "slurm_gpu_problems",
    "multiplier_label",
    "shard_job_config",
    "shard_jobs",
    "shard_path",
    "stages_off",
    "with_stages_off",
]

#: Folder of the simulated shards (rule simulate_shard).
SHARD_DIR = "results/simulate_shard"  # io.shards.WORKFLOW_SHARD_FOLDER: tested equal


def multiplier_label(a: float) -> str:
    """Path label of a concentration multiplier (``1.0`` → ``'1'``, ``0.5`` → ``'0.5'``)."""
    return f"{float(a):g}"


def shard_path(
    scene: str, shard: int, multiplier: float | None = None, root: str = SHARD_DIR
) -> str:
    """``<root>/<scene>/shard_<k>.h5`` or ``<root>/<scene>/a<a>/shard_<k>.h5``."""
    if multiplier is None:
        return f"{root}/{scene}/shard_{int(shard)}.h5"
    return f"{root}/{scene}/a{multiplier_label(multiplier)}/shard_{int(shard)}.h5"


def shard_jobs(config: Mapping[str, Any]) -> list[dict[str, Any]]:
    """One entry ``{scene, shard, multiplier, path}`` per shard the config asks for (none
    of the train scene when the estimator trains on a stream,
    :func:`subslope.config.shard_scenes`)."""
    config = _config.validate(config)
    jobs = []
    with_shards = _config.shard_scenes(config)
    for name, counts in config["simulation"]["scenes"].items():
        if name not in with_shards:
            continue
        scene, _ = resolved_scene(config, name)
        n_img = int(counts["images_per_shard"])
        if n_img % scene.images_per_set:
            raise _config.ConfigError(
                f"config key simulation.scenes.{name}.images_per_shard = {n_img} must be a "
                "multiple "
                f"of scenes.{name}.images_per_set = {scene.images_per_set}"
            )
        mults = scene_multipliers(config, scene)
        for k in range(int(counts["n_shards"])):
            for a in mults or (None,):
                jobs.append(
                    {"scene": name, "shard": k, "multiplier": a, "path": shard_path(name, k, a)}
                )
    return jobs


def derived_seed(seed: int, name: str) -> int:
    """A 32-bit seed for the stream ``name``, derived from the global ``seed``."""
    key = int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "little")
    return int(np.random.SeedSequence([int(seed), key]).generate_state(1)[0])


#: ``simulation.render`` keys that change how a shard job runs, not its images: they
#: reach the job from the workflow's config, not through its (rerun-triggering) params.


def shard_job_config(
    config: Mapping[str, Any], scene: str, multiplier: float | str | None = None
) -> dict[str, Any]:
    """The resolved configuration one shard job of ``scene`` needs, and nothing else.

    The validated sections that determine its images: ``seed``, ``instrument``,
    ``cosmology``, the scene's spec, its ``simulation.scenes`` entry, ``simulation.sources``
    and the render settings without :data:`RUN_ONLY_RENDER_KEYS`; for a CDM scene its own
    multiplier alone (every multiplier's shard shares the seed, so adding or removing
    another multiplier changes no existing job; null for the other scenes); whether the
    lens light is fitted (``simulation.light_fit`` resolved) and the lens-centre settings
    the fit starts from. Every stage is off
    (:func:`with_stages_off`), so the job's own validation checks only what the job
    uses. Passed to the job as a Snakemake param without its ``stages`` (which name no
    image), so a change of any of these values reruns exactly the shards it affects and
    a new stage reruns none.
    """
    config = _config.validate(config)
    sim = config["simulation"]
    sc, _ = resolved_scene(config, scene)
    mults = scene_multipliers(config, sc)
    kept: list[float] | None = None
    if mults is not None and multiplier is not None:
        a = float(multiplier)
        kept = [next(m for m in mults if abs(m - a) <= 1e-12 * max(abs(a), 1.0))]
    return {
        "seed": config["seed"],
        "instrument": config["instrument"],
        "cosmology": config["cosmology"],
        "scenes": {scene: (config.get("scenes") or {}).get(scene) or {}},
        "simulation": {
            "scenes": {scene: sim["scenes"][scene]},
            "multipliers": kept,
            "render": {k: v for k, v in sim["render"].items() if k not in RUN_ONLY_RENDER_KEYS},
            "sources": sim["sources"],
            "light_fit": _config.light_fit_enabled(config),
        },
        "hst": {"lens_centre": config["hst"]["lens_centre"]},
        "stages": stages_off(),
    }


def stages_off() -> dict[str, bool]:
    """Every stage flag off (a shard job's config checks only what the job uses)."""
    return {name: False for name in _config.STAGE_NEEDS}


def with_stages_off(job: Mapping[str, Any]) -> dict[str, Any]:
    """``job`` (a :func:`shard_job_config`, perhaps without its ``stages``) with every
    stage flag off."""
    return {**job, "stages": stages_off()}


def runnable_config(job: Mapping[str, Any], run: Mapping[str, Any]) -> dict[str, Any]:
    """The config a job of ``scene`` simulates with: its resolved sections ``job``
    (:func:`subslope.plan.shard_job_config`) plus, from the workflow's config ``run``,
    what changes no image: ``data`` (where the resources live) and the run-only render
    keys; sets the compile cache (:func:`subslope.render.kernels.use_compile_cache`)."""
    config = copy.deepcopy(with_stages_off(job))
    config["data"] = copy.deepcopy(run["data"])
    render = run["simulation"]["render"]
    config["simulation"]["render"].update({k: render[k] for k in RUN_ONLY_RENDER_KEYS})
    from subslope.render.kernels import use_compile_cache

    use_compile_cache(render.get("compile_cache"))
    return config


def plan_problems(config: Mapping[str, Any]) -> list[str]:
    """Problems of a schema-valid ``config`` that only its scenes, data registry and data
    catalogue show, each naming the key and what is allowed: every scene must build
    (:class:`subslope.simulation.scenes.Scene`), the COSMOS split fractions must sum to 1,
    a noise-correlation range must be ordered,
    every COSMOS folder and the empirical PSF file must be registered data or exist, and
    the HST systems
    named in ``hst`` must be in the catalogue (when the catalogue is at hand). Called by
    the workflow when it loads and by ``subslope validate-config``."""
    from subslope.simulation.priors import PriorError
    from subslope.simulation.scenes import SceneError, scenes_from_config

    config = _config.validate(config)
    problems: list[str] = []
    try:
        scenes_from_config(config.get("scenes"))
        for name in config["simulation"]["scenes"]:
            resolved_scene(config, name)
    except (SceneError, PriorError) as exc:
        problems.append(str(exc))
    else:
        problems += _cdm_series_problems(config)
    src = config["simulation"]["sources"]
    split = src["split"]
    total = sum(float(split[k]) for k in ("train", "validation", "test"))
    if not split.get("ids") and abs(total - 1.0) > 1e-9:
        problems.append(
            "config keys simulation.sources.split.train/validation/test = "
            f"{split['train']}/{split['validation']}/{split['test']} must sum to 1 "
            f"(they sum to {total:g})"
        )
    rho = config["instrument"]["noise_correlation"]
    if isinstance(rho, list) and rho[0] > rho[1]:
        problems.append(
            f"config key instrument.noise_correlation = {rho}: a range [low, high] needs "
            "low <= high"
        )
    problems += cache_folder_problems(config)
    problems += _cosmos_folder_problems(config)
    problems += _psf_problems(config)
    problems += _observation_problems(config)
    problems += _hst_name_problems(config)
    return problems


def _cdm_series_problems(config: Mapping[str, Any]) -> list[str]:
    """The matched EPL controls and the abundance series of a config whose CDM stage
    runs, checked against their resolved scenes (scenes with shards only: the missing
    ones are named by :func:`subslope.config.cross_key_problems`)."""
    if not _config.active_stages(config)["cdm_grid"]:
        return []
    grids, with_shards = _config.cdm_grids(config), _config.shard_scenes(config)
    problems: list[str] = []
    for key, name, kind in _config.cdm_series(config):
        if name not in with_shards:
            continue
        if kind in grids:
            problems += _control_problems(config, key, name, grids[kind][0])
        elif kind == "abundance":
            problems += _abundance_problems(config, key, name)
    return problems


def _control_problems(config: Mapping[str, Any], key: str, name: str, nfw: str) -> list[str]:
    """A matched EPL control ``name`` must carry EPL subhalos of one slope
    (``subhalos.fixed_gamma``), draw the CDM sets (``common_draws``) and have shards of
    the size of its grid's NFW scene ``nfw``, no more of them (each pairs with that
    scene's shard of the same index)."""
    sc, _ = resolved_scene(config, name)
    problems = []
    if sc.subhalos.fixed_gamma is None or not sc.common_draws:
        problems.append(
            f"config key {key} = {name!r}: a matched EPL control needs "
            f"scenes.{name}.subhalos.fixed_gamma (EPL subhalos of one slope) and "
            f"scenes.{name}.common_draws: true"
        )
    sim = config["simulation"]["scenes"]
    if nfw in sim and (
        sim[name]["images_per_shard"] != sim[nfw]["images_per_shard"]
        or sim[name]["n_shards"] > sim[nfw]["n_shards"]
    ):
        problems.append(
            f"config key {key} = {name!r}: simulation.scenes.{name} "
            f"({sim[name]['n_shards']} x {sim[name]['images_per_shard']}) must have the "
            f"images_per_shard of simulation.scenes.{nfw} "
            f"({sim[nfw]['n_shards']} x {sim[nfw]['images_per_shard']}) and at most as "
            "many shards: each control shard pairs with that scene's shard"
        )
    return problems


def _abundance_problems(config: Mapping[str, Any], key: str, name: str) -> list[str]:
    """A scene of the abundance series must be a CDM scene simulated at a = 1 with a
    subhalo count prior U{0, N_max}, in shards of the field grid's NFW scene's size."""
    sc, _ = resolved_scene(config, name)
    mults = scene_multipliers(config, sc) or ()
    count = sc.subhalos.count
    problems = []
    if sc.subhalos.profile == "epl" or 1.0 not in [float(a) for a in mults]:
        problems.append(
            f"config key {key} = {name!r}: the abundance series needs NFW or tNFW subhalos "
            f"simulated at a = 1 (multipliers {list(mults)})"
        )
    if count.dist != "uniform_int" or count.support[0] != 0:
        problems.append(
            f"config key {key} = {name!r}: scenes.{name}.subhalos.count must be a "
            "uniform_int prior from 0 (U{0, N_max})"
        )
    sim, nfw = config["simulation"]["scenes"], config["cdm"]["nfw_scene"]
    if nfw in sim and sim[name]["images_per_shard"] != sim[nfw]["images_per_shard"]:
        problems.append(
            f"config key {key} = {name!r}: simulation.scenes.{name}.images_per_shard must "
            f"equal simulation.scenes.{nfw}.images_per_shard: each shard pairs with that "
            "scene's subhalo-free re-render"
        )
    return problems


def _observation_problems(config: Mapping[str, Any]) -> list[str]:
    """A configured set of lenses (``observations.folder``) must match its manifest and
    every cutout must fit the simulated instrument
    (:mod:`subslope.io.observation_set`); the shipped set is checked by the registry."""
    from subslope.io.observation_set import (
        cutout_problems,
        manifest_problems,
        observation_folder,
    )

    folder, catalog, shipped = observation_folder(config)
    if shipped:
        return []
    if not folder.is_dir():
        return [f"config key observations.folder = {str(folder)!r}: no such folder"]
    problems = manifest_problems(folder, catalog) or cutout_problems(config, folder, catalog)
    return problems or _joint_fit_problems(config, folder, catalog)


def _joint_fit_problems(config: Mapping[str, Any], folder: Path, catalog: Path) -> list[str]:
    """The domain stage fits a joint lens-light prior to the set's lenses (rule
    fit_lens_light), which needs :data:`~subslope.physics.light.fit.MIN_JOINT_FITS`."""
    from subslope.io.observations import load_catalog
    from subslope.physics.light.fit import MIN_JOINT_FITS

    n = len(load_catalog(catalog))
    if not _config.active_stages(config)["domain"] or n >= MIN_JOINT_FITS:
        return []
    return [
        f"config key observations.folder = {str(folder)!r}: {catalog} lists {n} lens(es); "
        f"the domain stage (stages.domain) fits a joint lens-light prior to them, which "
        f"needs at least {MIN_JOINT_FITS}: add lenses, or set stages.domain: false"
    ]


def _not_registered(config, names, prefix: str, kind: str) -> tuple[list[str], str, str]:
    """Those of ``names`` that are neither registered data (paths, or for
    ``kind="folder"`` their first component) nor present under ``data.resources_dir`` as a
    ``kind`` ("file" or "folder"); with the registered ones starting with ``prefix`` and
    the resources folder, for the message."""
    from pathlib import Path

    from subslope.io.resources import load_registry

    paths = [e.path for e in load_registry()]
    registered = {p.split("/", 1)[0] for p in paths} if kind == "folder" else set(paths)
    root = Path(config["data"]["resources_dir"])
    present = Path.is_dir if kind == "folder" else Path.is_file
    missing = [n for n in names if n.strip("/") not in registered and not present(root / n)]
    known = ", ".join(sorted(r for r in registered if r.startswith(prefix)))
    return missing, known, str(root)


def _psf_problems(config: Mapping[str, Any]) -> list[str]:
    """The PSF file must be registered data or a file under the resources folder, and a
    file that is there must hold the PSF library the config asks for (read as the shard
    jobs read it), so that a wrong file stops the run before any job, naming key and
    file."""
    psf = config["instrument"]["psf"]
    if psf["source"] != "empirical":
        return []
    missing, known, root = _not_registered(config, [psf["file"]], "psf/", "file")
    if missing:
        return [
            f"config key instrument.psf.file = {name!r}: neither a registered data file "
            f"({known}) nor a file under data.resources_dir = {root}"
            for name in missing
        ]
    path = Path(root) / psf["file"]
    if not path.is_file():
        return []  # registered and not yet fetched: fetch_data checks its checksum
    from subslope.physics.instrument import load_empirical_psf

    try:
        which = "mean" if psf["index"] is None else int(psf["index"])
        load_empirical_psf(path, which, supersampling=int(psf["supersampling"]))
    except Exception as exc:  # astropy, numpy and our own checks raise alike
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return [
            f"config key instrument.psf.file = {psf['file']!r}: {path} is not a PSF library "
            f"of odd square FITS images with PSF {psf['index']} ({reason})"
        ]
    return []


#: Path keys of a config under which a run writes, with what it writes there: said
#: before the first job when one lies outside the project folder (variants do that on
#: purpose; a slip would write fetched data or shards somewhere unexpected).
OUTSIDE_KEYS = {
    "data.resources_dir": "fetches the reference data (HST, PSF, COSMOS) into",
    "simulation.shard_cache": "keeps a copy of every shard in",
    "simulation.render.compile_cache": "writes compiled kernels to",
    "systematics.folder": "writes the variant campaigns to",
    "systematics.shard_cache": "keeps the variants' shards in",
}


def project_root(start: str | os.PathLike[str]) -> Path:
    """The project folder of a config file at ``start``: its nearest ancestor holding a
    ``Snakefile`` (where the workflow runs and resolves relative paths), else the working
    directory."""
    for folder in Path(start).resolve().parents:
        if (folder / "Snakefile").is_file():
            return folder
    return Path.cwd()


def plan_warnings(config: Mapping[str, Any], root: str | os.PathLike[str] = ".") -> list[str]:
    """Legitimate but surprising choices, to log before the first job: a path key of
    :data:`OUTSIDE_KEYS` outside the project folder ``root`` (saying what the run writes
    there); a lens whose θ_E lies outside the training prior."""
    from subslope.io.observation_set import observation_folder

    base = Path(root).resolve()
    _, catalog, _ = observation_folder(config)
    out = theta_e_warnings(config, catalog) if catalog.is_file() else []
    for key, what in OUTSIDE_KEYS.items():
        value: Any = config
        for part in key.split("."):
            value = value.get(part) if isinstance(value, Mapping) else None
        if not value:
            continue
        path = (base / str(value)).resolve()
        if path != base and base not in path.parents:
            out.append(
                f"config key {key} = {value!r} lies outside the project folder {base}: the "
                f"run {what} {path}; its results still go to {base / 'results'}"
            )
    return out


def theta_e_warnings(config: Mapping[str, Any], catalog, scene: str = "train") -> list[str]:
    """Lenses of ``catalog`` whose θ_E lies outside the support of ``scene``'s θ_E prior:
    said before a run, not refused (four of the shipped 13 lie above the reference
    prior's 1.3″)."""
    from subslope.io.observations import ObservationError, load_catalog

    try:
        rows = load_catalog(catalog)
    except ObservationError:
        return []
    low, high = resolved_scene(config, scene)[0].main_lens.theta_e.support
    return [
        f"{row['system']} ({catalog}): theta_E_arcsec = {row['theta_E_arcsec']} lies outside "
        f"the training prior of scenes.{scene}.main_lens.theta_e, [{low:g}, {high:g}]"
        for row in rows
        if not low <= row["theta_E_arcsec"] <= high
    ]


def _cosmos_folder_problems(config: Mapping[str, Any]) -> list[str]:
    from subslope.io.observations import inside_folder

    folder = config["simulation"]["sources"]["folder"]
    names = folder if isinstance(folder, list) else [folder]
    outside = [n for n in names if not inside_folder(str(n))]
    if outside:
        return [
            f"config key simulation.sources.folder: {outside} must name folders inside "
            f"data.resources_dir = {config['data']['resources_dir']} (relative, no '..')"
        ]
    missing, known, root = _not_registered(config, names, "cosmos", "folder")
    if not missing:
        return []
    return [
        f"config key simulation.sources.folder: {missing} neither a registered data folder "
        f"({known}) nor a folder under data.resources_dir = {root}"
    ]


def _hst_name_problems(config: Mapping[str, Any]) -> list[str]:
    import csv
    from pathlib import Path

    from subslope.io.observation_set import observation_folder

    _, own, shipped = observation_folder(config)
    candidates = [own]
    if shipped and config["data"].get("mirror"):
        candidates.append(Path(config["data"]["mirror"]) / "hst" / "catalog.csv")
    catalog = next((p for p in candidates if p.is_file()), None)
    if catalog is None:
        return []
    with open(catalog, newline="", encoding="utf-8") as fh:  # no torch: read the names only
        known = [row.get("system", "") for row in csv.DictReader(fh)]
    hst = config["hst"]
    out = []
    for key in ("combine", "show", "highlight"):
        unknown = [s for s in (hst[key] or []) if s not in known]
        if unknown:
            out.append(
                f"config key hst.{key}: unknown system(s) {unknown}; the catalogue "
                f"{catalog} lists {', '.join(known)}"
            )
    return out


def slurm_gpu_problems(config: Mapping[str, Any], gres: str | None = None) -> list[str]:
    """GPU requests (``training.gpus``, ``inference.gpus``) of the stages that run, on a
    SLURM cluster whose nodes offer no GPU: SLURM refuses such a job only at submission
    ("Invalid generic resource (gres) specification"), after the jobs before it ran.

    ``gres`` is the output of ``sinfo -h -o %G`` (the generic resources of every node);
    by default ``sinfo`` is asked, and nothing is reported where it cannot be run.
    """
    import subprocess

    config = _config.validate(config)
    stages = _config.active_stages(config)
    asks = [
        (key, config[section]["gpus"])
        for key, section, stage in (
            ("training.gpus", "training", "train"),
            ("inference.gpus", "inference", "evaluate"),
        )
        if stages[stage] and config[section]["gpus"] > 0
    ]
    if not asks:
        return []
    if gres is None:
        try:
            gres = subprocess.run(
                ["sinfo", "-h", "-o", "%G"], capture_output=True, text=True, timeout=30
            ).stdout
        except (OSError, subprocess.SubprocessError):
            return []
    if "gpu" in gres:
        return []
    return [
        f"config key {key} = {n}: the SLURM cluster offers no GPU (sinfo shows generic "
        f"resources {gres.split() or ['(none)']}); set {key}: 0 and "
        f"{key.replace('gpus', 'device')}: cpu, or submit where GPU nodes are"
        for key, n in asks
    ]


# Records of a `snakemake -n`: the header of a grouped job, a job's rule line (indented
# under its group's header), and a rule file's `localrules:` block.
_GROUP = re.compile(r"^\[[^\]]*\] Group job (\S+) \(jobs in lexicogr\. order\):$")
_RECORD = re.compile(r"^( *)(?:local)?(?:rule|checkpoint) (\S+):$")
_LOCALRULES = re.compile(r"^localrules:\s*\n((?:[ \t]+[\w, ]+\n?)+)", re.MULTILINE)


def host_rules(root: str | Path = ".") -> set[str]:
    """Rules that never become cluster jobs: the ``localrules:`` of the Snakefile and
    ``workflow/rules/*.smk`` under ``root``, and ``all`` (no action)."""
    root = Path(root)
    names = {"all"}
    for path in [root / "Snakefile", *sorted((root / "workflow" / "rules").glob("*.smk"))]:
        if path.is_file():
            for block in _LOCALRULES.findall(path.read_text()):
                names.update(n for n in re.split(r"[\s,]+", block) if n)
    return names


def count_cluster_jobs(dry_run: str, local: set[str]) -> Counter[str]:
    """Cluster jobs per kind in the text of a ``snakemake -n``: a group job (its header,
    then its members' records indented) is one job, keyed ``group <name>: <member
    rules>``; an ungrouped job of a rule not in ``local`` is one job, keyed by its rule."""
    jobs: Counter[str] = Counter()
    group: tuple[str, set[str]] | None = None

    def close() -> None:
        if group is not None:
            jobs[f"group {group[0]}: {', '.join(sorted(group[1]))}"] += 1

    for line in dry_run.splitlines():
        if match := _GROUP.match(line):
            close()
            group = (match.group(1), set())
        elif match := _RECORD.match(line):
            indent, rule = match.groups()
            if indent and group is not None:
                group[1].add(rule)
            elif not indent:
                close()
                group = None
                if rule not in local:
                    jobs[rule] += 1
    close()
    return jobs


def cache_folder_problems(config: Mapping, root: str | os.PathLike[str] = ".") -> list[str]:
    """The cache folders of ``config`` (``simulation.shard_cache``,
    ``systematics.shard_cache``) that overlap the campaign's ``results/`` folder (are it,
    lie inside it or contain it), each naming the key: a cache beside the results would
    let ``subslope cache prune`` take a result for a cache entry."""
    base = Path(root).resolve()
    results = (base / "results").resolve()
    problems = []
    for key in ("simulation", "systematics"):
        folder = (config.get(key) or {}).get("shard_cache")
        if not folder:
            continue
        path = (base / folder).resolve()
        if path == results or results in path.parents or path in results.parents:
            problems.append(
                f"config key {key}.shard_cache = {folder!r} overlaps results/ ({results}); "
                "allowed: a folder outside results/, e.g. .cache/shard_cache"
            )
    return problems
