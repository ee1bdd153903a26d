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

    .venv/bin/python benchmarks/learning_curve.py --out results/learning_curve \\
        --curve hst=config/config.yaml:results/simulate_shard \\
        --curve table1=/tmp/table1.yaml --sizes 2000 4000 8000 --workers 2 --figure
"""

from __future__ import annotations

import argparse
import csv
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
            gamma.append(np.asarray(par["gamma_sub"]))
            sets.append(np.asarray(par["set_index"]) + 10**6 * k)
    return g, np.concatenate(prof), np.concatenate(gamma), np.concatenate(sets)


def held_out_metrics(g, prof, gamma, sets, n: int, level: float = 0.68) -> dict:
    """ρ, median interval width and prior-edge fraction of held-out stacks of ``n``
    images (one a set: its first ``n``), with the conformal threshold of the other half
    of the sets (:func:`subslope.stats.calibration.split`)."""
    from scipy.stats import spearmanr

    from subslope.stages.calibrate import safe_threshold
    from subslope.stats import calibration as cal
    from subslope.stats import intervals as iv

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
    label, config_path, resources, inputs, augment, n, out, sim_seconds = args
    import torch

    torch.set_num_threads(1)
    from subslope.nre.train import load_estimator, train
    from subslope.nre.whitening import compute_whitening
    from subslope.stages.train import input_transform, training_section

    light_fit = inputs == "light_subtracted"
    config = _config(config_path, resources, light_fit)
    config["training"]["inputs"] = inputs
    config["training"]["augment"] = augment
    shards = Path(out) / label / _shard_folder(out, label, light_fit)
    per_shard = config["simulation"]["scenes"]["train"]["images_per_shard"]
    train_paths = [str(shards / "train" / f"shard_{k}.h5") for k in range(n // per_shard)]
    val = sorted(map(str, (shards / "validation").glob("shard_*.h5")))
    test = sorted(map(str, (shards / "test_epl").glob("shard_*.h5")), key=_index)
    suffix = "" if augment == "none" else f"_{augment}"
    run = Path(out) / label / "runs" / f"{inputs}{suffix}_n{n}"
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
        return [{"augment": "none", **r} for r in csv.DictReader(fh)]


def _append_row(path: Path, row: dict) -> None:
    """Append ``row``; a table with an older header is rewritten with :data:`COLUMNS`."""
    old = _read_rows(path)
    header = None
    if path.exists():
        with open(path) as fh:
            header = next(csv.reader(fh), None)
    if old and header != list(COLUMNS):
        tmp = path.with_suffix(".tmp")
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(old)
        os.replace(tmp, path)
    new = not path.exists()
    with open(path, "a", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        if new:
            w.writeheader()
        w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        fh.flush()
        os.fsync(fh.fileno())


def _curve_key(row: dict) -> tuple[str, ...]:
    """(curve, transform) and the augmentation where there is one."""
    aug = row.get("augment", "none")
    return (row["curve"], row["inputs"]) + (() if aug == "none" else (aug,))


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
    done = {(r["curve"], r["inputs"], r["augment"], int(r["n_train"])) for r in _read_rows(table)}
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
                for augment in args.augment:
                    for n in sizes[label]:
                        if (label, inputs, augment, n) not in done:
                            runs.append(
                                (label, config_path, args.resources, inputs, augment, n)
                                + (str(args.out), sim)
                            )
        for future in as_completed([pool.submit(_run_task, r) for r in runs]):
            row = future.result()
            _append_row(table, row)
            print(json.dumps(row), flush=True)
    if args.figure:
        trends = figure(_read_rows(table), args.out / "learning_curve.png")
        (args.out / "trend.json").write_text(json.dumps(trends, indent=2))
        print(json.dumps(trends, indent=2))


if __name__ == "__main__":
    main()
