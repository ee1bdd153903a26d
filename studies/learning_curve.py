"""Learning curve of the reduced estimator: what it reads of γ against the number of
training images, for each input transform (subslope.nre.inputs), on the HST-matched
scene of the reduced config and on the lens light of the paper's Table 1 (reference).

Per curve (``--curve LABEL=CONFIG[:SHARDS]``) the shards of the scenes train,
validation and test_epl are made first, every one with its lens-light fit: copied from
the campaign's ``SHARDS`` folder with the fit added
(:func:`subslope.stages.simulate.attach_light_fit`), or, without a folder, simulated
from ``CONFIG`` with ``simulation.light_fit`` on. Then, for every transform and
training size n (the first n/1000 training shards), the config's estimator is trained
(whitening after the transform, early stopping on the validation shard) and evaluated:

- ``val_loss``: the best validation loss (ln 2 = 0.693 is an estimator that reads nothing);
- ``rho``, ``rho_p``: Spearman ρ of the 13-stack γ_MLE against the true γ on the held-out
  half of the test_epl sets (one stack a set: 200 stacks for the reduced config's 400);
- ``width_1``, ``width_13``: the median 68% interval width of held-out single images
  (validation shard) and 13-stacks, with the conformal thresholds of the other half;
- ``edge_13``: the fraction of held-out 13-stacks whose γ_MLE is at a prior edge;
- ``core_hours``: training + evaluation (1 thread), and ``sim_core_hours``: making the
  n training images (shard wall time, light fit included) per 1 core.

Rows go to ``OUT/learning_curve.csv`` as each run finishes (a rerun skips finished
runs); ``--figure`` draws ``OUT/learning_curve.png`` and fits ρ = a + b ln n per curve
(:func:`trend`). Work runs in ``--workers`` processes of one thread each.
``--training-seeds`` repeats the runs with other training seeds (``_seedS`` run
folders); ``--readouts SIMULATE_SHARD`` reads, with every trained run of the first
curve, the 13 HST lenses and a campaign's a = 1 CDM sets (:func:`readouts`:
``OUT/readouts.csv``), which is where trainings that agree in-distribution can differ.

    .venv/bin/python studies/learning_curve.py --out results/learning_curve \\
        --curve hst=config/config.yaml:results/simulate_shard \\
        --curve table1=/tmp/table1.yaml --sizes 2000 4000 8000 --workers 2 --figure
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

SCENES = ("train", "validation", "test_epl")
COLUMNS = (
    "curve",
    "inputs",
    "augment",
    "training_seed",
    "n_train",
    "val_loss",
    "epochs",
    "rho",
    "rho_p",
    "n_stacks",
    "width_1",
    "width_13",
    "edge_13",
    "core_hours",
    "sim_core_hours",
)


def _config(path: str, resources: str | None, light_fit: bool = True) -> dict:
    from subslope import config as cfgmod

    config = cfgmod.load(path, env=False)
    if resources:
        config["data"]["resources_dir"] = resources
    config["simulation"]["light_fit"] = bool(light_fit)
    if not light_fit and config["training"]["inputs"] == "light_subtracted":
        config["training"]["inputs"] = "whitened"  # the runs set their own transform
    return cfgmod.validate(config)


def _shard_task(args) -> tuple[str, float]:
    """Make one shard, with its lens-light fit when ``light_fit``; returns its path and
    the core-seconds it cost (for a campaign shard: its campaign job's, from the
    benchmark file beside it, plus the fit), kept in ``<shard>.seconds`` for reruns.
    Without the fit a campaign shard is linked, not copied."""
    config_path, resources, scene, index, source, dst, light_fit = args
    import torch

    torch.set_num_threads(1)
    from subslope.stages.simulate import attach_light_fit, simulate_shard

    seconds = Path(dst + ".seconds")
    if not seconds.exists():
        config = _config(config_path, resources, light_fit)
        counts = config["simulation"]["scenes"][scene]
        counts["n_shards"] = max(int(counts["n_shards"]), index + 1)
        Path(dst).parent.mkdir(parents=True, exist_ok=True)
        t = time.perf_counter()
        if source and Path(source).exists():
            if light_fit:
                attach_light_fit(config, source, dst)
            else:
                Path(dst).unlink(missing_ok=True)
                os.symlink(Path(source).resolve(), dst)
            before = _simulation_seconds(source, scene, index)
        else:
            simulate_shard(config, scene, index, dst, overwrite=True)
            before = 0.0
        seconds.write_text(f"{time.perf_counter() - t + before:.3f}\n")
    return dst, float(seconds.read_text())


def _simulation_seconds(source: str, scene: str, index: int) -> float:
    """What simulating ``source`` cost: its ``.seconds`` file when an earlier curve made
    it, else its campaign job's benchmark file (``results/benchmarks/simulate_shard``),
    else 0. A linked shard is timed where it really lives."""
    own = Path(source + ".seconds")
    if own.exists():
        return float(own.read_text())
    real = Path(source).resolve()
    job = real.parents[2] / "benchmarks" / "simulate_shard" / scene / f"shard_{index}.tsv"
    if not job.exists():
        return 0.0
    with open(job) as f:
        return float(next(csv.DictReader(f, delimiter="\t"))["s"])


def shard_tasks(
    curves, out: Path, resources, n_train_shards: int, light_fit: bool = True
) -> list[tuple]:
    """One task per shard of every curve: (config, resources, scene, index, source, dst,
    light_fit); training shards beyond the campaign's are simulated (shard k is the same
    file in a campaign of any size). Shards with the fit and without it live in separate
    folders (``shards`` and ``shards_nofit``)."""
    folder_name = "shards" if light_fit else "shards_nofit"
    tasks = []
    for label, (config_path, folder) in curves.items():
        config = _config(config_path, resources, light_fit)
        for scene in SCENES:
            n = config["simulation"]["scenes"][scene]["n_shards"]
            n = n_train_shards[label] if scene == "train" else n
            for k in range(n):
                src = str(Path(folder) / scene / f"shard_{k}.h5") if folder else ""
                dst = str(out / label / folder_name / scene / f"shard_{k}.h5")
                tasks.append((config_path, resources, scene, k, src, dst, light_fit))
    return tasks


def _profiles(model, meta, paths):
    """ln r̂ of every image of ``paths`` and the images' true γ and set ids."""
    from subslope.io.shards import open_shard
    from subslope.nre.evaluate import estimator_profiles
    from subslope.nre.inputs import InputTransform, ShardLightModels
    from subslope.stats.intervals import gamma_grid

    g = gamma_grid()
    needs = InputTransform.from_json(meta.get("inputs")).needs_light
    prof, gamma, sets = [], [], []
    for k, p in enumerate(paths):
        with open_shard(p) as s:
            par = s.params
            light = ShardLightModels(p, s.file) if needs else None
            prof.append(
                estimator_profiles(
                    model,
                    meta,
                    s.images,
                    par["theta_e"],
                    par["lens_x"],
                    par["lens_y"],
                    g,
                    light=light,
                    device="cpu",
                )
            )
            label = par["gamma_sub"] if "gamma_sub" in par else np.full(len(s.images), np.nan)
            gamma.append(np.asarray(label))
            sets.append(np.asarray(par["set_index"]) + 10**6 * k)
    return g, np.concatenate(prof), np.concatenate(gamma), np.concatenate(sets)


def held_out_metrics(g, prof, gamma, sets, n: int, level: float = 0.68) -> dict:
    """ρ, median interval width and prior-edge fraction of held-out stacks of ``n``
    images (one a set: its first ``n``), with the conformal threshold of the other half
    of the sets (:func:`subslope.stats.calibration.split`)."""
    from scipy.stats import spearmanr

    from subslope.stats import calibration as cal
    from subslope.stats import intervals as iv
    from subslope.stats.calibration import safe_threshold

    stacks = cal.make_stacks(gamma, sets, n, mode="independent")
    stacked = iv.stack(prof, stacks.indices)
    calib = cal.split(stacks.set_id, seed=0, fraction=0.5)
    tau, _ = safe_threshold(cal.stack_t_true(prof, g, stacks)[calib], level)
    tau = max(tau, 1e-6)
    held = [iv.interval(p, g, tau) for p in stacked[~calib]]
    mle = np.array([h.mle for h in held])
    rho, p_value = spearmanr(stacks.gamma[~calib], mle)
    return {
        "rho": float(rho),
        "rho_p": float(p_value),
        "n_stacks": len(held),
        "width": float(np.median([h.upper - h.lower for h in held])),
        "edge": float(np.mean([h.lower_at_edge or h.upper_at_edge for h in held])),
    }


def _run_task(args) -> dict:
    """Train and evaluate one (curve, transform, n); the row of the CSV."""
    label, config_path, resources, inputs, augment, seed, n, out, sim_seconds = args
    import torch

    torch.set_num_threads(1)
    from subslope.nre.train import load_estimator, train
    from subslope.nre.whitening import compute_whitening
    from subslope.stages.train import input_transform, training_section

    light_fit = inputs == "light_subtracted"
    config = _config(config_path, resources, light_fit)
    config["training"]["inputs"] = inputs
    config["training"]["augment"] = augment
    if seed != "":
        config["training"]["seed"] = int(seed)
    shards = Path(out) / label / _shard_folder(out, label, light_fit)
    per_shard = config["simulation"]["scenes"]["train"]["images_per_shard"]
    train_paths = [str(shards / "train" / f"shard_{k}.h5") for k in range(n // per_shard)]
    val = sorted(map(str, (shards / "validation").glob("shard_*.h5")))
    test = sorted(map(str, (shards / "test_epl").glob("shard_*.h5")), key=_index)
    suffix = "" if augment == "none" else f"_{augment}"
    run = Path(out) / label / "runs" / f"{inputs}{suffix}_n{n}{_seed_suffix(seed)}"
    t = time.perf_counter()
    white = compute_whitening(train_paths, run / "whitening.json", inputs=input_transform(config))
    summary = train(training_section(config), train_paths, val, white, run, run / "ckpt")
    model, meta = load_estimator(summary["model"])
    single = held_out_metrics(*_profiles(model, meta, val), 1)
    per_set = int(config["scenes"]["test_epl"]["images_per_set"])
    stack = held_out_metrics(*_profiles(model, meta, test), per_set)
    return {
        "curve": label,
        "inputs": inputs,
        "augment": augment,
        "training_seed": seed,
        "n_train": n,
        "val_loss": summary["best_val_loss"],
        "epochs": summary["epochs"],
        "rho": stack["rho"],
        "rho_p": stack["rho_p"],
        "n_stacks": stack["n_stacks"],
        "width_1": single["width"],
        "width_13": stack["width"],
        "edge_13": stack["edge"],
        "core_hours": (time.perf_counter() - t) / 3600,
        "sim_core_hours": sim_seconds * n / per_shard / 3600,
    }


READOUT_COLUMNS = (
    "curve",
    "run",
    "hst_mle",
    "hst_lower",
    "hst_upper",
    "hst_closed",
    "tau_13",
    "nfw_p16",
    "nfw_p50",
    "nfw_p84",
    "nfw_edge",
    "tnfw_p16",
    "tnfw_p50",
    "tnfw_p84",
    "tnfw_edge",
    "n_cdm_sets",
)


def readouts(out: Path, label: str, config_path: str, resources, run: Path, cdm: Path) -> dict:
    """What one trained run reads of the data and of CDM: the combined 13-lens HST
    interval and the stack γ_MLE of the a = 1 NFW and tNFW sets (median, 16–84%, the
    fraction at a prior edge), all with the 13-stack threshold τ_13 of every test_epl set
    (:func:`subslope.stats.calibration.safe_threshold`). ``cdm``: a campaign's
    ``simulate_shard`` folder (``nfw/a1``, ``tnfw/a1``); their shards get the lens-light
    fit in ``OUT/LABEL/cdm_fit`` when the run's inputs need it."""
    import torch

    torch.set_num_threads(1)
    from subslope.nre.inputs import InputTransform
    from subslope.nre.train import load_estimator
    from subslope.stages.hst import hst_profiles
    from subslope.stages.simulate import attach_light_fit
    from subslope.stats import calibration as cal
    from subslope.stats import intervals as iv
    from subslope.stats.calibration import safe_threshold

    model, meta = load_estimator(run / "model.pt")
    light_fit = InputTransform.from_json(meta.get("inputs")).needs_light
    config = _config(config_path, resources, light_fit)
    shards = out / label / _shard_folder(out, label, light_fit)
    test = sorted(map(str, (shards / "test_epl").glob("shard_*.h5")), key=_index)
    g, prof, gamma, sets = _profiles(model, meta, test)
    stacks = cal.make_stacks(gamma, sets, 13, mode="independent")
    tau, _ = safe_threshold(cal.stack_t_true(prof, g, stacks), 0.68)
    data = Path(config["data"]["resources_dir"])
    _, _, hst, _ = hst_profiles(
        run / "model.pt",
        data / "hst",
        g,
        lens_centre=config["hst"]["lens_centre"],
        pixel_scale=config["instrument"]["pixel_scale"],
        device="cpu",
        config=config,
    )
    combined = iv.interval(iv.stack(hst), g, tau)
    row = {
        "curve": label,
        "run": run.name,
        "hst_mle": combined.mle,
        "hst_lower": combined.lower,
        "hst_upper": combined.upper,
        "hst_closed": not (combined.lower_at_edge or combined.upper_at_edge),
        "tau_13": float(tau),
    }
    for scene in ("nfw", "tnfw"):
        paths = sorted(map(str, (cdm / scene / "a1").glob("shard_*.h5")), key=_index)
        if light_fit:
            fitted = out / label / "cdm_fit" / scene
            for k, p in enumerate(paths):
                if not (fitted / Path(p).name).exists():
                    fitted.mkdir(parents=True, exist_ok=True)
                    attach_light_fit(config, p, fitted / Path(p).name)
                paths[k] = str(fitted / Path(p).name)
        _, cprof, _, csets = _profiles(model, meta, paths)
        held = [iv.interval(iv.stack(cprof[csets == s]), g, tau) for s in np.unique(csets)]
        mle = np.array([h.mle for h in held])
        p16, p50, p84 = np.quantile(mle, [0.16, 0.5, 0.84])
        row |= {
            f"{scene}_p16": float(p16),
            f"{scene}_p50": float(p50),
            f"{scene}_p84": float(p84),
            f"{scene}_edge": float(np.mean([h.lower_at_edge or h.upper_at_edge for h in held])),
            "n_cdm_sets": len(held),
        }
    return row


def _readout_task(args) -> dict:
    return readouts(*args)


def _write_readouts(pool, args, curves) -> None:
    """:func:`readouts` of every run of the first curve not yet in ``OUT/readouts.csv``."""
    label, (config_path, _) = next(iter(curves.items()))
    table = args.out / "readouts.csv"
    done = {r["run"] for r in _read_rows(table)}
    runs = sorted(p.parent for p in (args.out / label / "runs").glob("*/model.pt"))
    tasks = [
        (args.out, label, config_path, args.resources, run, args.readouts)
        for run in runs
        if run.name not in done
    ]
    for row in pool.map(_readout_task, tasks):
        _append_row(table, row, READOUT_COLUMNS)
        print(json.dumps(row), flush=True)


def _seed_suffix(seed) -> str:
    """Run-folder suffix of a training seed other than the config's (``""``)."""
    return "" if seed == "" else f"_seed{seed}"


def _shard_folder(out, label: str, light_fit: bool) -> str:
    """``shards`` (with the lens-light fit) for runs that need the fit, and for the others
    too when this output folder has no fit-free shards (earlier runs made only those)."""
    nofit = Path(out) / label / "shards_nofit"
    return "shards" if light_fit or not nofit.exists() else "shards_nofit"


def _index(path: str) -> int:
    return int(Path(path).stem.split("_")[-1])


def trend(n, rho, n_stacks, target: float = 0.9, draws: int = 4000, seed: int = 0):
    """Weighted fit ρ = a + b ln n (errors of Fisher's z, 1/sqrt(N − 3), mapped back) and
    the n where the line reaches ``target``: median and 16–84% of Monte Carlo draws of
    (a, b) from the fit's covariance (``inf`` where the slope is not positive). An
    undefined ρ (every held-out γ_MLE the same: an estimator that reads nothing) counts
    as 0."""
    x = np.log(np.asarray(n, float))
    y = np.nan_to_num(np.asarray(rho, float), nan=0.0)
    sigma = (1 - np.clip(y, -0.99, 0.99) ** 2) / np.sqrt(np.asarray(n_stacks, float) - 3)
    if x.size < 2:
        return {"a": math.nan, "b": math.nan, "n_target": (math.nan,) * 3}
    design = np.column_stack([np.ones_like(x), x]) / sigma[:, None]
    cov = np.linalg.inv(design.T @ design)
    coef = cov @ design.T @ (y / sigma)
    ab = np.random.default_rng(seed).multivariate_normal(coef, cov, size=draws)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        n_t = np.where(ab[:, 1] > 0, np.exp((target - ab[:, 0]) / ab[:, 1]), np.inf)
    q = np.quantile(n_t, [0.5, 0.16, 0.84], method="inverted_cdf")
    return {"a": float(coef[0]), "b": float(coef[1]), "n_target": tuple(map(float, q))}


def _read_rows(path: Path) -> list[dict]:
    """The table's rows; rows of tables written before the ``augment`` column read
    ``none`` there."""
    if not path.exists():
        return []
    with open(path) as fh:
        return [{"augment": "none", "training_seed": "", **r} for r in csv.DictReader(fh)]


def _append_row(path: Path, row: dict, columns: tuple[str, ...] = COLUMNS) -> None:
    """Append ``row``; a table with an older header is rewritten with ``columns``."""
    old = _read_rows(path)
    header = None
    if path.exists():
        with open(path) as fh:
            header = next(csv.reader(fh), None)
    if old and header != list(columns):
        tmp = path.with_suffix(".tmp")
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
            w.writeheader()
            w.writerows(old)
        os.replace(tmp, path)
    new = not path.exists()
    with open(path, "a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns)
        if new:
            w.writeheader()
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        fh.flush()
        os.fsync(fh.fileno())


def _curve_key(row: dict) -> tuple[str, ...]:
    """(curve, transform) and the augmentation and training seed where there are ones."""
    aug, seed = row.get("augment", "none"), row.get("training_seed", "")
    return (
        (row["curve"], row["inputs"])
        + (() if aug == "none" else (aug,))
        + (() if seed == "" else (f"seed{seed}",))
    )


def figure(rows: list[dict], path: Path) -> dict:
    """Validation loss and ρ against n per (curve, transform, augmentation), with the ρ
    trends; returns the trends by ``curve/inputs[/augment]``."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_l, ax_r) = plt.subplots(1, 2, figsize=(10, 4))
    trends = {}
    for key in sorted({_curve_key(r) for r in rows}):
        sel = sorted((r for r in rows if _curve_key(r) == key), key=lambda r: int(r["n_train"]))
        n = np.array([int(r["n_train"]) for r in sel])
        rho = np.nan_to_num([float(r["rho"]) for r in sel], nan=0.0)
        ns = np.array([int(r["n_stacks"]) for r in sel])
        name = "/".join(key)
        ax_l.plot(n, [float(r["val_loss"]) for r in sel], "o-", label=name)
        ax_r.errorbar(n, rho, (1 - rho**2) / np.sqrt(ns - 3), fmt="o-", label=name)
        trends[name] = trend(n, rho, ns)
    ax_l.axhline(math.log(2), color="k", lw=0.8, ls=":")
    for ax, lab in ((ax_l, "best validation loss"), (ax_r, "Spearman ρ, 13-stacks")):
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("training images n")
        ax.set_ylabel(lab)
    ax_r.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return trends


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--curve", action="append", required=True, metavar="LABEL=CONFIG[:SHARDS]")
    ap.add_argument("--inputs", nargs="+", default=["whitened", "snr", "light_subtracted"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[2000, 4000, 8000])
    ap.add_argument(
        "--reference-inputs",
        nargs="+",
        default=["whitened"],
        help="transforms of every curve after the first",
    )
    ap.add_argument(
        "--reference-sizes",
        nargs="+",
        type=int,
        default=None,
        help="training sizes of every curve after the first (default: --sizes)",
    )
    ap.add_argument(
        "--augment",
        nargs="+",
        default=["none"],
        choices=["none", "dihedral"],
        help="training.augment of the runs (every curve)",
    )
    ap.add_argument(
        "--training-seeds",
        nargs="+",
        default=["config"],
        help="training.seed of the runs: integers, or 'config' for the config's own",
    )
    ap.add_argument(
        "--readouts",
        type=Path,
        default=None,
        metavar="SIMULATE_SHARD",
        help="also read the HST lenses and the a = 1 CDM sets (a campaign's simulate_shard "
        "folder) with every trained run of the first curve: OUT/readouts.csv",
    )
    ap.add_argument("--resources", default=None, help="data folder (default: the config's)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--figure", action="store_true")
    args = ap.parse_args(argv)
    curves = {}
    for spec in args.curve:
        label, rest = spec.split("=", 1)
        config_path, _, folder = rest.partition(":")
        curves[label] = (config_path, folder)
    args.out.mkdir(parents=True, exist_ok=True)
    table = args.out / "learning_curve.csv"
    done = {
        (r["curve"], r["inputs"], r["augment"], r["training_seed"], int(r["n_train"]))
        for r in _read_rows(table)
    }
    seeds = ["" if s == "config" else str(int(s)) for s in args.training_seeds]
    light_fit = "light_subtracted" in set(args.inputs) | set(args.reference_inputs)
    sizes = {
        label: args.sizes if k == 0 else (args.reference_sizes or args.sizes)
        for k, label in enumerate(curves)
    }
    n_train = {
        label: max(v)
        // _config(curves[label][0], args.resources)["simulation"]["scenes"]["train"][
            "images_per_shard"
        ]
        for label, v in sizes.items()
    }
    tasks = shard_tasks(curves, args.out, args.resources, n_train, light_fit)
    with ProcessPoolExecutor(args.workers) as pool:
        cost = {}
        for dst, sec in pool.map(_shard_task, tasks):
            cost.setdefault(Path(dst).parent, []).append(sec)
            print(f"shard {dst}: {sec:.1f} s", flush=True)
        runs = []
        for k, (label, (config_path, _)) in enumerate(curves.items()):
            folder = "shards" if light_fit else "shards_nofit"
            sim = float(np.median(cost[args.out / label / folder / "train"]))
            for inputs in args.inputs if k == 0 else args.reference_inputs:
                for augment, seed, n in itertools.product(args.augment, seeds, sizes[label]):
                    if (label, inputs, augment, seed, n) not in done:
                        runs.append(
                            (label, config_path, args.resources, inputs, augment, seed, n)
                            + (str(args.out), sim)
                        )
        for future in as_completed([pool.submit(_run_task, r) for r in runs]):
            row = future.result()
            _append_row(table, row)
            print(json.dumps(row), flush=True)
        if args.readouts:
            _write_readouts(pool, args, curves)
    if args.figure:
        trends = figure(_read_rows(table), args.out / "learning_curve.png")
        (args.out / "trend.json").write_text(json.dumps(trends, indent=2))
        print(json.dumps(trends, indent=2))


if __name__ == "__main__":
    main()
