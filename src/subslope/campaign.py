"""Glue of the campaign workflow: what each thin Snakemake script of the later stages calls.

The statistics live in :mod:`subslope.inference` and :mod:`subslope.calibration`, the
figures in :mod:`subslope.figures`, training in :mod:`subslope.nre`. This module connects
them to files:

| function | rule | writes |
|---|---|---|
| :func:`training_section`, :func:`run_training` | train_estimator | ``model.pt``, ``training_log.csv`` |
| :func:`plot_training_curves` | plot_training_curves | training-curve figure |
| :func:`evaluate_shard` | evaluate_profiles | profiles HDF5 of one shard (:func:`write_profiles`) |
| :func:`calibrate_stack_size` | calibrate_threshold | ``N{n}.npz`` |
| :func:`summarize_coverage` | summarize_coverage | ``calibration.csv``, ``thresholds.json``, coverage figure |
| :func:`measure_cdm_grid` | measure_cdm_grid | ``cdm_grid.npz``/``.csv``, figure 4 |
| :func:`find_lens_centre`, :func:`analyze_hst` | analyze_hst | ``profiles.h5``, ``intervals.csv``, figures 5, 6 |
| :func:`plot_validation` | plot_validation | figures 2, 3 |
| :func:`write_summary` | write_summary | ``summary.md`` and CSVs beside it |

Profiles files (one per evaluated shard) hold ``log_ratio (B, G)`` (ln r̂ on the grid,
float64), ``gammas (G,)``, ``gamma_true (B,)`` (NaN for CDM scenes, which have no label),
``set_index (B,)`` (images of one set share γ), ``c_multiplier (B,)`` (NaN for EPL
scenes), ``theta_e``, ``lens_x``, ``lens_y`` (the mask geometry used), and attributes
naming the scene, shard, estimator and run.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import json
import logging
import math
import os
import tempfile
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from subslope import calibration as cal
from subslope import inference as inf

__all__ = [
    "PROFILE_FIELDS",
    "derived_seed",
    "save_figure",
    "training_section",
    "checkpoint_key",
    "run_training",
    "plot_training_curves",
    "write_profiles",
    "read_profiles",
    "evaluate_shard",
    "safe_threshold",
    "calibrate_stack_size",
    "summarize_coverage",
    "load_thresholds",
    "threshold_for",
    "set_stacks",
    "measure_cdm_grid",
    "find_lens_centre",
    "analyze_hst",
    "plot_validation",
    "read_benchmarks",
    "spearman_trend",
    "write_summary",
]

log = logging.getLogger(__name__)

#: Datasets of a profiles file (besides ``gammas``).
PROFILE_FIELDS = ("log_ratio", "gamma_true", "set_index", "c_multiplier", "theta_e", "lens_x", "lens_y")


def _atomic_path(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    return Path(tmp)


def _write_text(path, text: str) -> Path:
    path = Path(path)
    tmp = _atomic_path(path)
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


def _write_csv(path, rows: Sequence[Mapping[str, Any]], columns: Sequence[str] | None = None) -> Path:
    import pandas as pd

    frame = pd.DataFrame(list(rows), columns=None if columns is None else list(columns))
    return _write_text(path, frame.to_csv(index=False))


def save_figure(fig, stem, *, run_name: str, dpi: int = 150) -> list[Path]:
    """Write ``stem.pdf`` and ``stem.png`` atomically, with ``run_name=<name>`` in the file
    metadata (PDF Subject, PNG Description) besides the footer drawn on the figure."""
    stem = Path(stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    title = fig.get_suptitle() or stem.name
    paths = []
    for fmt, meta in (("pdf", {"Title": title, "Subject": f"run_name={run_name}"}),
                      ("png", {"Title": title, "Description": f"run_name={run_name}"})):
        out = stem.parent / f"{stem.name}.{fmt}"
        tmp = _atomic_path(out)
        try:
            fig.savefig(tmp, format=fmt, dpi=dpi, metadata=meta)
            os.replace(tmp, out)
        finally:
            tmp.unlink(missing_ok=True)
        paths.append(out)
    return paths


def derived_seed(seed: int, name: str) -> int:
    """A 32-bit seed for the stream ``name``, derived from the global ``seed``."""
    key = int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "little")
    return int(np.random.SeedSequence([int(seed), key]).generate_state(1)[0])


# ---------------------------------------------------------------------------------------
# training
# ---------------------------------------------------------------------------------------
#: Keys of the config's ``training`` section that steer the workflow, not subslope.nre.train.
_WORKFLOW_TRAINING_KEYS = ("device", "threads", "gpus", "mem_mb", "runtime")


def training_section(config: Mapping[str, Any]) -> dict[str, Any]:
    """The ``subslope.nre.train`` config from the workflow config (validated, defaults filled).

    ``seed: null`` becomes a seed derived from the global seed; ``arch`` keys that are
    null take the preset's value; the pixel scale comes from ``instrument``; workflow-only
    keys (device, threads, gpus, mem_mb, runtime) are dropped; no progress bar.
    """
    tr = copy.deepcopy(dict(config["training"]))
    for key in _WORKFLOW_TRAINING_KEYS:
        tr.pop(key, None)
    tr["arch"] = {k: v for k, v in dict(tr.get("arch") or {}).items() if v is not None}
    if tr.get("seed") is None:
        tr["seed"] = derived_seed(config["seed"], "training")
    tr["pixel_scale"] = float(config["instrument"]["pixel_scale"])
    tr["progress"] = False
    return tr


def checkpoint_key(training: Mapping[str, Any], train_shards: Sequence, val_shards: Sequence,
                   data_hashes: Mapping[str, str] | None = None) -> str:
    """12 hex digits naming the checkpoint folder of one training run.

    Depends on the training section (without the resume-safe keys) and on the data
    (shard paths and the simulation hashes of their scenes), so a restarted job with the
    same inputs resumes while a changed config or data starts a fresh folder.
    """
    from subslope.nre.train import config_hash, resolve_config

    payload = {
        "training": config_hash(resolve_config(training)),
        "train": [os.fspath(p) for p in train_shards],
        "val": [os.fspath(p) for p in val_shards],
        "data": dict(data_hashes or {}),
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:12]


def run_training(training: Mapping[str, Any], train_shards: Sequence, val_shards: Sequence, whitening,
                 out_dir, ckpt_dir, *, device: str = "auto") -> dict[str, Any]:
    """Train (resuming from ``ckpt_dir`` when possible); ``out_dir`` gets model.pt + training_log.csv."""
    from subslope.nre.train import train

    dev = None if device in (None, "auto") else device
    summary = train(training, list(train_shards), list(val_shards), whitening, out_dir, ckpt_dir, device=dev)
    if not summary["finished"]:
        raise RuntimeError(f"training stopped before the end ({summary}); run again to resume from {ckpt_dir}")
    return summary


def plot_training_curves(log_csv, stem, *, run_name: str, source: str | None = None) -> list[Path]:
    """Training and validation loss (and learning rate) per epoch, from ``training_log.csv``."""
    import pandas as pd
    from matplotlib.figure import Figure

    from subslope.figures import _footer

    frame = pd.read_csv(log_csv)
    fig = Figure(figsize=(5.6, 4.2))
    ax = fig.subplots()
    ax.plot(frame["epoch"], frame["train_loss"], "o-", label="training loss", color="#444444")
    ax.plot(frame["epoch"], frame["val_loss"], "s-", label="validation loss", color="#c2185b")
    ax.axhline(math.log(2), color="0.6", ls=":", lw=1, label="chance (ln 2)")
    best = int(frame["val_loss"].idxmin())
    ax.plot(frame["epoch"][best], frame["val_loss"][best], "*", ms=12, color="#c2185b", label="best (kept)")
    ax.set_xlabel("epoch")
    ax.set_ylabel("NRE loss (binary cross-entropy)")
    if "lr" in frame:
        ax2 = ax.twinx()
        ax2.plot(frame["epoch"], frame["lr"], color="0.5", lw=0.8, ls="--")
        ax2.set_yscale("log")
        ax2.set_ylabel("learning rate (dashed)", color="0.4")
    ax.legend(fontsize=8, frameon=False)
    ax.grid(alpha=0.25)
    fig.suptitle("Estimator training curves", fontsize=10)
    _footer(fig, run_name, source)
    fig.subplots_adjust(bottom=0.16, top=0.9, right=0.86)
    return save_figure(fig, stem, run_name=run_name)


# ---------------------------------------------------------------------------------------
# profiles files
# ---------------------------------------------------------------------------------------
def write_profiles(path, *, log_ratio, gammas, gamma_true=None, set_index=None, c_multiplier=None,
                   theta_e=None, lens_x=None, lens_y=None, attrs: Mapping[str, Any] | None = None) -> Path:
    """Write one profiles file (atomic: temporary file, then ``os.replace``)."""
    path = Path(path)
    lr = np.asarray(log_ratio, dtype=np.float64)
    g = np.asarray(gammas, dtype=np.float64)
    if lr.ndim != 2 or lr.shape[1] != g.size:
        raise ValueError(f"log_ratio must have shape (B, G={g.size}), got {lr.shape}")
    b = lr.shape[0]

    def col(v, dtype, fill):
        a = np.full(b, fill, dtype=dtype) if v is None else np.asarray(v, dtype=dtype)
        if a.shape != (b,):
            raise ValueError(f"per-image arrays must have shape ({b},), got {a.shape}")
        return a

    data = {
        "log_ratio": lr,
        "gamma_true": col(gamma_true, np.float64, np.nan),
        "set_index": col(set_index, np.int64, 0) if set_index is not None else np.arange(b, dtype=np.int64),
        "c_multiplier": col(c_multiplier, np.float64, np.nan),
        "theta_e": col(theta_e, np.float64, np.nan),
        "lens_x": col(lens_x, np.float64, np.nan),
        "lens_y": col(lens_y, np.float64, np.nan),
    }
    tmp = _atomic_path(path)
    try:
        with h5py.File(tmp, "w") as fh:
            fh.create_dataset("gammas", data=g)
            for k, v in data.items():
                fh.create_dataset(k, data=v)
            for k, v in (attrs or {}).items():
                fh.attrs[k] = v if isinstance(v, (int, float, str, np.number)) else json.dumps(v, default=str)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def read_profiles(paths) -> dict[str, np.ndarray]:
    """Concatenate profiles files: every field of :data:`PROFILE_FIELDS`, ``gammas`` and
    ``set_id`` (a set id unique across the files: ``set_index`` made distinct per file)."""
    paths = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    if not paths:
        raise ValueError("read_profiles: no files")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in PROFILE_FIELDS}
    set_id = []
    gammas = None
    offset = 0
    for p in paths:
        with h5py.File(p, "r") as fh:
            g = fh["gammas"][...]
            if gammas is None:
                gammas = g
            elif g.shape != gammas.shape or not np.allclose(g, gammas):
                raise ValueError(f"{p}: gamma grid differs from the first file's")
            for k in PROFILE_FIELDS:
                parts[k].append(fh[k][...])
        _, inv = np.unique(parts["set_index"][-1], return_inverse=True)
        set_id.append(inv.astype(np.int64) + offset)
        offset += int(inv.max()) + 1 if inv.size else 0
    out = {k: np.concatenate(v) for k, v in parts.items()}
    out["gammas"] = gammas
    out["set_id"] = np.concatenate(set_id)
    return out


def evaluate_shard(model_path, shard_path, out_path, *, gammas, batch_size: int = 64, device: str = "auto",
                   run_name: str = "") -> Path:
    """ln r̂ of every image of a shard on the grid ``gammas``, written with :func:`write_profiles`."""
    from subslope.nre.train import load_estimator

    model, meta = load_estimator(model_path)
    prep = meta.get("preprocess", {})
    with h5py.File(shard_path, "r") as fh:
        params = {k: fh[f"params/{k}"][...] for k in ("theta_e", "lens_x", "lens_y")}
        for k in ("gamma_sub", "set_index", "c_multiplier"):
            params[k] = fh[f"params/{k}"][...] if f"params/{k}" in fh else None
        scene = fh.attrs.get("scene", "")
        profiles = inf.log_ratio_profiles(
            model, fh["images"], params["theta_e"], params["lens_x"], params["lens_y"], meta["whitening"], gammas,
            batch_size=batch_size, device=None if device in (None, "auto") else device,
            pixel_scale=prep.get("pixel_scale", 0.04), mask_factor=prep.get("mask_factor", 1.5),
        )
    attrs = {"scene": str(scene), "shard": os.fspath(shard_path), "model": os.fspath(model_path),
             "model_config_hash": str(meta.get("config_hash", "")), "run_name": run_name}
    return write_profiles(out_path, log_ratio=profiles, gammas=gammas, gamma_true=params["gamma_sub"],
                          set_index=params["set_index"], c_multiplier=params["c_multiplier"],
                          theta_e=params["theta_e"], lens_x=params["lens_x"], lens_y=params["lens_y"], attrs=attrs)


# ---------------------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------------------
def safe_threshold(t, level: float) -> tuple[float, bool]:
    """``(τ, exact)``: the conformal threshold of :func:`subslope.calibration.threshold`, or,
    when the sample is too small for that level (rank > n), the largest ``t`` with
    ``exact=False`` (tiny test campaigns); NaN for an empty sample."""
    t = np.asarray(t, dtype=np.float64)
    if t.size == 0:
        return float("nan"), False
    k = math.ceil((t.size + 1) * level)
    if k > t.size:
        return float(np.max(t)), False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cal.FewSamplesWarning)
        return float(cal.threshold(t, level)), True


def calibrate_stack_size(profile_paths, n: int, out_npz, *, level: float = 0.68, seed: int = 0,
                         heldout_fraction: float = 0.5, levels=None) -> dict[str, Any]:
    """Threshold τ_N and held-out coverage for stacks of ``n`` images; writes ``out_npz``.

    Stacks: :func:`subslope.calibration.make_stacks` (disjoint N-subsets of every set of
    images sharing γ, seeded). Split by set (:func:`subslope.calibration.split`):
    ``heldout_fraction`` of the sets are held out. ``tau`` uses all stacks (the threshold
    for new data), ``tau_calibration`` the calibration part only, whose held-out coverage
    is reported (with Wilks' χ²₁ threshold for comparison) along with expected-coverage
    curves over ``levels`` (default 0.01…0.99).

    The npz holds: n, level, tau, tau_exact, tau_calibration, tau_wilks, t_true, gamma,
    set_id, is_calibration, indices, levels, coverage_curve, coverage_curve_wilks, and the
    scalars of the coverage (coverage, coverage_err, wilson_lo, wilson_hi, coverage_wilks,
    coverage_wilks_err, n_calibration, n_heldout). Returns the same as a dict.
    """
    data = read_profiles(profile_paths)
    ok = np.isfinite(data["gamma_true"])
    if not ok.all():
        raise ValueError(f"calibration needs labelled images; {int((~ok).sum())} have no gamma_true")
    rng = np.random.default_rng(derived_seed(seed, f"stacks/N{int(n)}"))
    stacks = cal.make_stacks(data["gamma_true"], data["set_id"], int(n), rng)
    t_true = cal.stack_t_true(data["log_ratio"], data["gammas"], stacks)
    lv = np.linspace(0.01, 0.99, 99) if levels is None else np.asarray(levels, dtype=np.float64)
    tau, exact = safe_threshold(t_true, level)
    tau_w = cal.wilks_threshold(level)
    try:
        is_cal = cal.split(stacks.set_id, seed=derived_seed(seed, "split"), fraction=1.0 - heldout_fraction)
    except ValueError:  # a single set: nothing to hold out
        is_cal = np.ones(len(stacks), dtype=bool)
    t_cal, t_held = t_true[is_cal], t_true[~is_cal]
    tau_cal, _ = safe_threshold(t_cal, level)
    cov = dict(coverage=np.nan, coverage_err=np.nan, wilson_lo=np.nan, wilson_hi=np.nan,
               coverage_wilks=np.nan, coverage_wilks_err=np.nan)
    curve = np.full(lv.size, np.nan)
    curve_w = np.full(lv.size, np.nan)
    if t_held.size:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cal.FewSamplesWarning)
            p, err, (wlo, whi) = cal.coverage(t_held, tau_cal)
            pw, errw, _ = cal.coverage(t_held, tau_w)
            _, curve_w = cal.wilks_coverage(t_held, lv)
            curve = np.array([np.mean(t_held <= safe_threshold(t_cal, a)[0]) for a in lv])
        cov = dict(coverage=p, coverage_err=err, wilson_lo=wlo, wilson_hi=whi, coverage_wilks=pw, coverage_wilks_err=errw)
    out = dict(n=int(n), level=float(level), tau=tau, tau_exact=bool(exact), tau_calibration=tau_cal, tau_wilks=tau_w,
               t_true=t_true, gamma=stacks.gamma, set_id=stacks.set_id, is_calibration=is_cal, indices=stacks.indices,
               levels=lv, coverage_curve=curve, coverage_curve_wilks=curve_w,
               n_calibration=int(is_cal.sum()), n_heldout=int((~is_cal).sum()), **cov)
    out_npz = Path(out_npz)
    tmp = _atomic_path(out_npz)
    with open(tmp, "wb") as fh:
        np.savez(fh, **out)
    os.replace(tmp, out_npz)
    log.info("N=%d: %d stacks, tau=%.4g (exact %s), held-out coverage %.3f (Wilks %.3f)", n, len(stacks), tau,
             exact, cov["coverage"], cov["coverage_wilks"])
    return out


_TABLE_COLUMNS = ("n_images", "n_stacks", "tau", "tau_exact", "tau_wilks", "tau_calibration", "n_calibration",
                  "n_heldout", "coverage", "coverage_err", "wilson_lo", "wilson_hi", "coverage_wilks",
                  "coverage_wilks_err", "level")


def summarize_coverage(npz_paths, out_csv, out_json, fig_stem, *, run_name: str, source: str | None = None):
    """Table of every N (``calibration.csv``), the thresholds (``thresholds.json``:
    ``{"level", "tau": {N: τ_N}, "exact": {N: bool}, "wilks"}``) and the coverage figure."""
    import pandas as pd

    from subslope.figures import coverage_figure

    rows, curves, curves_w = [], {}, {}
    levels = None
    for p in npz_paths:
        with np.load(p) as z:
            n = int(z["n"])
            rows.append({"n_images": n, "n_stacks": int(z["t_true"].size), "tau": float(z["tau"]),
                         "tau_exact": bool(z["tau_exact"]), "tau_wilks": float(z["tau_wilks"]),
                         "tau_calibration": float(z["tau_calibration"]), "n_calibration": int(z["n_calibration"]),
                         "n_heldout": int(z["n_heldout"]), "coverage": float(z["coverage"]),
                         "coverage_err": float(z["coverage_err"]), "wilson_lo": float(z["wilson_lo"]),
                         "wilson_hi": float(z["wilson_hi"]), "coverage_wilks": float(z["coverage_wilks"]),
                         "coverage_wilks_err": float(z["coverage_wilks_err"]), "level": float(z["level"])})
            levels = z["levels"]
            curves[n], curves_w[n] = z["coverage_curve"], z["coverage_curve_wilks"]
    table = pd.DataFrame(rows, columns=_TABLE_COLUMNS).sort_values("n_images").reset_index(drop=True)
    _write_text(out_csv, table.to_csv(index=False))
    thr = {"level": float(table["level"].iloc[0]), "wilks": float(table["tau_wilks"].iloc[0]),
           "tau": {str(int(r.n_images)): float(r.tau) for r in table.itertuples()},
           "exact": {str(int(r.n_images)): bool(r.tau_exact) for r in table.itertuples()}}
    _write_text(out_json, json.dumps(thr, indent=2) + "\n")
    plot_table = table.fillna({"coverage": np.nan})
    fig = coverage_figure(plot_table, levels, {k: np.nan_to_num(v, nan=0.0) for k, v in sorted(curves.items())},
                          {k: np.nan_to_num(v, nan=0.0) for k, v in sorted(curves_w.items())},
                          run_name=run_name, source=source)
    save_figure(fig, fig_stem, run_name=run_name)
    return table, thr


def load_thresholds(path) -> dict[str, Any]:
    """``thresholds.json`` of :func:`summarize_coverage` with integer N keys."""
    with open(path, encoding="utf-8") as fh:
        thr = json.load(fh)
    thr["tau"] = {int(k): float(v) for k, v in thr["tau"].items()}
    thr["exact"] = {int(k): bool(v) for k, v in thr.get("exact", {}).items()}
    return thr


def threshold_for(thresholds: Mapping[str, Any], n: int) -> tuple[float, int]:
    """``(τ, N used)``: τ_N if N was calibrated, else the largest calibrated N below it
    (logged as a warning: the interval is then not calibrated for this stack size)."""
    taus = thresholds["tau"]
    if n in taus:
        return taus[n], n
    below = [k for k in taus if k <= n] or list(taus)
    k = max(below) if any(k <= n for k in taus) else min(taus)
    log.warning("no threshold calibrated for N=%d; using tau_%d (the interval is not calibrated)", n, k)
    return taus[k], k


def set_stacks(data: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One stack per set (all images sharing γ): stacked profiles ``(S, G)``, ``mle (S,)``,
    ``gamma_true (S,)``, ``c_multiplier (S,)``, ``n_images (S,)``."""
    ids, inv = np.unique(data["set_id"], return_inverse=True)
    stacked = inf.stack(data["log_ratio"], inv)
    first = np.array([np.flatnonzero(inv == k)[0] for k in range(ids.size)], dtype=np.int64)
    return {"profiles": stacked, "mle": np.atleast_1d(inf.mle(stacked, data["gammas"])),
            "gamma_true": data["gamma_true"][first], "c_multiplier": data["c_multiplier"][first],
            "n_images": np.bincount(inv, minlength=ids.size)}


# ---------------------------------------------------------------------------------------
# concentration grid (figure 4)
# ---------------------------------------------------------------------------------------
def measure_cdm_grid(files: Mapping[tuple[str, float], Sequence], out_npz, out_csv, fig_stem, *, run_name: str,
                     nfw_scene: str = "nfw", tnfw_scene: str | None = "tnfw", band=(16, 84),
                     source: str | None = None):
    """Stack MLEs (one per simulated set) for every (scene, multiplier) of ``files``.

    ``files[(scene, a)]``: the profiles files of that scene at multiplier ``a``. Writes the
    MLEs (``out_npz``: multipliers, mles_<scene> (n_a, n_sets) padded with NaN), the
    per-(scene, a) median and ``band`` percentiles (``out_csv``: scene, multiplier,
    n_sets, n_images, median, lo, hi) and figure 4. Returns the table.
    """
    import pandas as pd

    from subslope.figures import concentration_grid

    mults = sorted({float(a) for _, a in files})
    scenes = [s for s in (nfw_scene, tnfw_scene) if s is not None and any(k[0] == s for k in files)]
    rows, arrays = [], {"multipliers": np.asarray(mults)}
    for scene in scenes:
        per_a = []
        for a in mults:
            paths = files.get((scene, a))
            if not paths:
                per_a.append(np.array([]))
                continue
            st = set_stacks(read_profiles(paths))
            per_a.append(st["mle"])
            lo, med, hi = np.percentile(st["mle"], [band[0], 50, band[1]])
            rows.append({"scene": scene, "multiplier": a, "n_sets": int(st["mle"].size),
                         "n_images": int(np.median(st["n_images"])), "median": med, "lo": lo, "hi": hi})
        width = max(1, max(m.size for m in per_a))
        mat = np.full((len(mults), width), np.nan)
        for i, m in enumerate(per_a):
            mat[i, :m.size] = m
        arrays[f"mles_{scene}"] = mat
    table = pd.DataFrame(rows, columns=["scene", "multiplier", "n_sets", "n_images", "median", "lo", "hi"])
    out_npz = Path(out_npz)
    tmp = _atomic_path(out_npz)
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)
    os.replace(tmp, out_npz)
    _write_text(out_csv, table.to_csv(index=False))
    n_img = int(table["n_images"].median()) if len(table) else 13
    fig = concentration_grid(mults, arrays[f"mles_{nfw_scene}"],
                             arrays.get(f"mles_{tnfw_scene}") if tnfw_scene else None,
                             run_name=run_name, source=source, n_images=n_img,
                             percentiles=(band[0], 50, band[1]))
    save_figure(fig, fig_stem, run_name=run_name)
    return table


def cdm_band(table, scene: str, multiplier: float = 1.0) -> tuple[float, float, float] | None:
    """``(median, lo, hi)`` of ``scene`` at ``multiplier`` from a cdm_grid table (or None)."""
    if table is None or not len(table):
        return None
    sel = table[(table["scene"] == scene) & np.isclose(table["multiplier"], multiplier)]
    if not len(sel):
        return None
    r = sel.iloc[0]
    return float(r["median"]), float(r["lo"]), float(r["hi"])


__all__ += ["cdm_band"]


# ---------------------------------------------------------------------------------------
# HST
# ---------------------------------------------------------------------------------------
def _pixel_coords(n: int, pixel_scale: float) -> np.ndarray:
    return (np.arange(n) - (n - 1) / 2.0) * pixel_scale


def find_lens_centre(image, *, pixel_scale: float = 0.04, method: str = "light_centroid", smoothing: float = 1.0,
                     search_radius: float = 0.4, aperture: float = 0.3, peak_fraction: float = 0.5,
                     iterations: int = 3) -> tuple[float, float]:
    """Lens centre ``(x, y)`` in arcsec (package pixel convention, ``image[j, i]`` at ``(x_i, y_j)``).

    ``light_centroid``: smooth the image with a Gaussian of ``smoothing`` pixels, take the
    brightest smoothed pixel within ``search_radius`` of the image centre (the lens light
    dominates there; arcs lie near θ_E ≈ 1″, outside), then iterate ``iterations`` times:
    the light-weighted centroid, within ``aperture`` of the current estimate, of the
    brightest pixels: weights ``smoothed − peak_fraction · (aperture maximum)``, clipped at
    0. Only the core above that level counts, so faint arcs, subhalo perturbations and
    noise in the aperture barely pull the centroid; on simulated images (lens light
    mag 17–19, COSMOS arcs, noise) the error stays below 0.25 pixel
    (tests/test_campaign.py). ``image_centre``: (0, 0).
    """
    if method == "image_centre":
        return 0.0, 0.0
    if method != "light_centroid":
        raise ValueError(f"unknown lens-centre method {method!r} (light_centroid, image_centre)")
    from scipy.ndimage import gaussian_filter

    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {img.shape}")
    sm = gaussian_filter(np.nan_to_num(img), smoothing) if smoothing > 0 else np.nan_to_num(img)
    xs = _pixel_coords(img.shape[1], pixel_scale)
    ys = _pixel_coords(img.shape[0], pixel_scale)
    xx, yy = np.meshgrid(xs, ys)
    near = np.hypot(xx, yy) <= max(search_radius, pixel_scale)
    j, i = np.unravel_index(np.argmax(np.where(near, sm, -np.inf)), sm.shape)
    cx, cy = float(xs[i]), float(ys[j])
    for _ in range(int(iterations)):
        sel = np.hypot(xx - cx, yy - cy) <= max(aperture, pixel_scale)
        a = sm[sel]
        w = np.clip(a - peak_fraction * a.max(), 0.0, None)
        tot = w.sum()
        if not tot > 0:
            break
        cx, cy = float((w * xx[sel]).sum() / tot), float((w * yy[sel]).sum() / tot)
    return cx, cy


def analyze_hst(model_path, hst_folder, thresholds_json, out_h5, out_csv, fig5_stem, fig6_stem, *, run_name: str,
                gammas, cdm_csv=None, combine: Sequence[str] | None = None, show: Sequence[str] = (),
                highlight: Sequence[str] = ("SDSSJ0946+1006",), lens_centre: Mapping[str, Any] | None = None,
                pixel_scale: float = 0.04, batch_size: int = 16, device: str = "auto",
                nfw_scene: str = "nfw", tnfw_scene: str | None = "tnfw"):
    """Profiles, intervals and figures 5–6 of the real HST lenses.

    Every cutout goes through the same pre-processing as the simulations (training
    whitening, 1.5 θ_E mask) with θ_E from the catalogue and the lens centre measured by
    :func:`find_lens_centre`. Individual intervals use τ_1; the combined stack of the
    ``combine`` systems (default all) uses τ_N, N = their number. Writes ``out_h5``
    (names, log_ratio, gammas, theta_e, lens_x, lens_y, combined), ``out_csv`` (one row per
    system and one ``combined`` row: mle, lower, upper, threshold, threshold_n, flags) and
    the figures; the a = 1 NFW/tNFW bands of figure 6 come from ``cdm_csv`` when given.
    """
    import pandas as pd

    from subslope.figures import hst_combined, hst_profiles
    from subslope.nre.train import load_estimator
    from subslope.observations import load_hst

    obs = load_hst(hst_folder)
    names = [o.name for o in obs]
    combine = list(names) if combine is None else list(combine)
    unknown = sorted((set(combine) | set(show) | set(highlight)) - set(names))
    if unknown:
        raise ValueError(f"hst: unknown system(s) {unknown}; catalogued: {names}")
    centres = [find_lens_centre(o.image, pixel_scale=pixel_scale, **dict(lens_centre or {})) for o in obs]
    images = np.stack([o.image for o in obs]).astype(np.float32)
    theta_e = np.array([o.theta_e for o in obs])
    lx, ly = np.array([c[0] for c in centres]), np.array([c[1] for c in centres])
    model, meta = load_estimator(model_path)
    prep = meta.get("preprocess", {})
    prof = inf.log_ratio_profiles(model, images, theta_e, lx, ly, meta["whitening"], gammas, batch_size=batch_size,
                                  device=None if device in (None, "auto") else device,
                                  pixel_scale=prep.get("pixel_scale", pixel_scale),
                                  mask_factor=prep.get("mask_factor", 1.5))
    g = np.asarray(gammas, dtype=np.float64)
    thr = load_thresholds(thresholds_json)
    tau1, n1 = threshold_for(thr, 1)
    rows = []
    for k, name in enumerate(names):
        iv = inf.interval(prof[k], g, tau1)
        rows.append({"system": name, "n_images": 1, "threshold_n": n1, "lens_x": lx[k], "lens_y": ly[k],
                     "theta_e": theta_e[k], **iv.as_dict()})
    idx = [names.index(s) for s in combine]
    combined = inf.stack(prof[idx])
    tau_c, n_c = threshold_for(thr, len(idx))
    iv_c = inf.interval(combined, g, tau_c)
    rows.append({"system": "combined", "n_images": len(idx), "threshold_n": n_c, "lens_x": np.nan,
                 "lens_y": np.nan, "theta_e": np.nan, **iv_c.as_dict()})
    table = pd.DataFrame(rows)
    _write_text(out_csv, table.to_csv(index=False))
    out_h5 = Path(out_h5)
    tmp = _atomic_path(out_h5)
    with h5py.File(tmp, "w") as fh:
        fh.create_dataset("names", data=np.array(names, dtype="S"))
        fh.create_dataset("log_ratio", data=prof)
        fh.create_dataset("gammas", data=g)
        fh.create_dataset("theta_e", data=theta_e)
        fh.create_dataset("lens_x", data=lx)
        fh.create_dataset("lens_y", data=ly)
        fh.create_dataset("combined", data=combined)
        fh.create_dataset("combined_systems", data=np.array(combine, dtype="S"))
        fh.attrs["run_name"] = run_name
        fh.attrs["model"] = os.fspath(model_path)
    os.replace(tmp, out_h5)
    source = f"estimator {meta.get('config_hash', '')}"
    shown = {s: prof[names.index(s)] for s in (show or names)}
    fig5 = hst_profiles(g, shown, tau1, run_name=run_name, source=source, kind="log_ratio",
                        wilks=cal.wilks_threshold(thr.get("level", 0.68)), highlight=tuple(highlight))
    save_figure(fig5, fig5_stem, run_name=run_name)
    cdm = pd.read_csv(cdm_csv) if cdm_csv else None
    bn = cdm_band(cdm, nfw_scene)
    bt = cdm_band(cdm, tnfw_scene) if tnfw_scene else None
    fig6 = hst_combined(g, combined, tau_c, None if bn is None else bn[1:], None if bt is None else bt[1:],
                        interval=iv_c, run_name=run_name, source=source, kind="log_ratio", n_images=len(idx))
    save_figure(fig6, fig6_stem, run_name=run_name)
    return table


# ---------------------------------------------------------------------------------------
# figures 2 and 3
# ---------------------------------------------------------------------------------------
def plot_validation(single_paths, stack_paths, thresholds_json, fig2_stem, fig3_stem, *, run_name: str,
                    source: str | None = None) -> dict[str, Any]:
    """Figure 2 (single images, τ_1) and figure 3 (whole sets of the stack scene, τ_N with
    N = images per set). Returns the Spearman trend of the stack MLEs (:func:`spearman_trend`)."""
    from subslope.figures import stack_scatter, validation_scatter

    thr = load_thresholds(thresholds_json)
    single = read_profiles(single_paths)
    g = single["gammas"]
    tau1, _ = threshold_for(thr, 1)
    ivs = inf.intervals(single["log_ratio"], g, tau1)
    fig2 = validation_scatter(single["gamma_true"], [i.mle for i in ivs], [i.lower for i in ivs],
                              [i.upper for i in ivs], run_name=run_name, source=source, threshold=tau1,
                              open_lower=[i.lower_at_edge for i in ivs], open_upper=[i.upper_at_edge for i in ivs],
                              prior=(float(g[0]), float(g[-1])))
    save_figure(fig2, fig2_stem, run_name=run_name)
    st = set_stacks(read_profiles(stack_paths))
    n = int(np.median(st["n_images"]))
    tau_n, _ = threshold_for(thr, n)
    ivs = inf.intervals(st["profiles"], g, tau_n)
    fig3 = stack_scatter(st["gamma_true"], [i.mle for i in ivs], [i.lower for i in ivs], [i.upper for i in ivs],
                         run_name=run_name, n_images=n, source=source, threshold=tau_n,
                         open_lower=[i.lower_at_edge for i in ivs], open_upper=[i.upper_at_edge for i in ivs],
                         prior=(float(g[0]), float(g[-1])))
    save_figure(fig3, fig3_stem, run_name=run_name)
    return spearman_trend(st["gamma_true"], st["mle"])


# ---------------------------------------------------------------------------------------
# summary
# ---------------------------------------------------------------------------------------
def spearman_trend(gamma_true, mle) -> dict[str, float]:
    """Spearman rank correlation between true γ and the MLE: ``{rho, p_value, n}``."""
    from scipy import stats

    gt, m = np.asarray(gamma_true, dtype=np.float64), np.asarray(mle, dtype=np.float64)
    ok = np.isfinite(gt) & np.isfinite(m)
    if ok.sum() < 3 or np.ptp(m[ok]) == 0 or np.ptp(gt[ok]) == 0:
        return {"rho": float("nan"), "p_value": float("nan"), "n": int(ok.sum())}
    res = stats.spearmanr(gt[ok], m[ok])
    return {"rho": float(res.statistic), "p_value": float(res.pvalue), "n": int(ok.sum())}


def read_benchmarks(paths_by_stage: Mapping[str, Sequence]) -> list[dict[str, Any]]:
    """Per stage: number of jobs, summed wall time (s), longest job (s) and peak RSS (MB),
    from Snakemake benchmark TSV files (columns ``s``, ``max_rss``). Missing files count 0."""
    import pandas as pd

    rows = []
    for stage, paths in paths_by_stage.items():
        secs, longest, rss, n = 0.0, 0.0, 0.0, 0
        for p in paths:
            if not os.path.exists(p):
                continue
            frame = pd.read_csv(p, sep="\t")
            if not len(frame):
                continue
            s = float(frame["s"].iloc[-1])
            secs, longest, n = secs + s, max(longest, s), n + 1
            mr = pd.to_numeric(frame.get("max_rss", pd.Series([np.nan])), errors="coerce").iloc[-1]
            if np.isfinite(mr):
                rss = max(rss, float(mr))
        rows.append({"stage": stage, "jobs": n, "seconds": round(secs, 2), "longest_job_s": round(longest, 2),
                     "peak_rss_mb": round(rss, 1)})
    return rows


def _fmt(x, digits: int = 3) -> str:
    try:
        return "n/a" if x is None or not math.isfinite(float(x)) else f"{float(x):.{digits}f}"
    except (TypeError, ValueError):
        return str(x)


def _md_table(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    body = "".join("| " + " | ".join(_fmt(r.get(c)) if isinstance(r.get(c), float) else str(r.get(c, ""))
                                     for c in columns) + " |\n" for r in rows)
    return head + body


#: Section headings of summary.md, in order.
SUMMARY_SECTIONS = ("Configuration", "HST measurement", "CDM predictions (a = 1)", "Calibration and coverage",
                    "Estimator trend", "Run time per stage")
__all__ += ["SUMMARY_SECTIONS"]


def write_summary(out_md, *, run_name: str, config_hash: str, config_file: str = "", hst_csv=None,
                  cdm_csv=None, calibration_csv=None, trend: Mapping[str, float] | None = None,
                  benchmarks: Mapping[str, Sequence] | None = None, nfw_scene: str = "nfw",
                  tnfw_scene: str | None = "tnfw") -> Path:
    """``summary.md`` and, beside it, ``hst_result.csv``, ``cdm_prediction.csv``,
    ``coverage.csv``, ``trend.csv`` and ``stage_runtime.csv``. Any input may be None (its
    stage was off): the section then says so."""
    import pandas as pd

    out_md = Path(out_md)
    folder = out_md.parent
    folder.mkdir(parents=True, exist_ok=True)
    lines = [f"# subslope campaign summary: `{run_name}`\n"]

    lines.append(f"## {SUMMARY_SECTIONS[0]}\n")
    items = [f"- run_name: `{run_name}`", f"- config hash: `{config_hash}`"]
    if config_file:
        items.append(f"- config file(s): `{config_file}`")
    lines.append("\n".join(items) + "\n")

    lines.append(f"## {SUMMARY_SECTIONS[1]}\n")
    if hst_csv:
        hst = pd.read_csv(hst_csv)
        comb = hst[hst["system"] == "combined"].iloc[0]
        row = {"n_images": int(comb["n_images"]), "gamma_mle": float(comb["mle"]), "lower": float(comb["lower"]),
               "upper": float(comb["upper"]), "minus": float(comb["mle"] - comb["lower"]),
               "plus": float(comb["upper"] - comb["mle"]), "threshold": float(comb["threshold"]),
               "threshold_n": int(comb["threshold_n"]), "lower_at_edge": bool(comb["lower_at_edge"]),
               "upper_at_edge": bool(comb["upper_at_edge"]), "multimodal": bool(comb["multimodal"])}
        _write_csv(folder / "hst_result.csv", [row])
        note = []
        if row["threshold_n"] != row["n_images"]:
            note.append(f"threshold from N = {row['threshold_n']}, NOT calibrated for N = {row['n_images']}")
        if row["lower_at_edge"] or row["upper_at_edge"]:
            note.append("open at the prior edge")
        if row["multimodal"]:
            note.append("hull of several regions")
        lines.append(f"Combined stack of {row['n_images']} HST lenses: γ_MLE = {row['gamma_mle']:.3f} "
                     f"(−{row['minus']:.3f}, +{row['plus']:.3f}) at {_fmt(row['threshold'])} "
                     f"(68% interval [{row['lower']:.3f}, {row['upper']:.3f}])"
                     + (f"; {'; '.join(note)}" if note else "") + ".\n")
        singles = hst[hst["system"] != "combined"].to_dict("records")
        lines.append(_md_table(singles, ["system", "mle", "lower", "upper", "lower_at_edge", "upper_at_edge"]))
    else:
        _write_csv(folder / "hst_result.csv", [], ["n_images", "gamma_mle", "lower", "upper", "minus", "plus",
                                                  "threshold", "threshold_n", "lower_at_edge", "upper_at_edge",
                                                  "multimodal"])
        lines.append("Stage `hst` not run.\n")

    lines.append(f"## {SUMMARY_SECTIONS[2]}\n")
    if cdm_csv:
        cdm = pd.read_csv(cdm_csv)
        rows = []
        for scene in (nfw_scene, tnfw_scene):
            if scene is None:
                continue
            b = cdm_band(cdm, scene)
            if b is not None:
                n_sets = int(cdm[(cdm["scene"] == scene) & np.isclose(cdm["multiplier"], 1.0)]["n_sets"].iloc[0])
                rows.append({"scene": scene, "median": b[0], "p16": b[1], "p84": b[2], "n_sets": n_sets})
        _write_csv(folder / "cdm_prediction.csv", rows, ["scene", "median", "p16", "p84", "n_sets"])
        lines.append("Median and 16–84% range of the stack γ_MLE of simulated CDM sets at a = 1:\n")
        lines.append(_md_table(rows, ["scene", "median", "p16", "p84", "n_sets"]) if rows else "no a = 1 sets\n")
    else:
        _write_csv(folder / "cdm_prediction.csv", [], ["scene", "median", "p16", "p84", "n_sets"])
        lines.append("Stage `cdm_grid` not run.\n")

    lines.append(f"## {SUMMARY_SECTIONS[3]}\n")
    if calibration_csv:
        table = pd.read_csv(calibration_csv)
        _write_text(folder / "coverage.csv", table.to_csv(index=False))
        lines.append("Held-out coverage of the 68% intervals with the calibrated threshold τ_N "
                     "(and with Wilks' χ²₁ threshold):\n")
        lines.append(_md_table(table.to_dict("records"),
                               ["n_images", "n_stacks", "tau", "tau_exact", "coverage", "coverage_err",
                                "coverage_wilks", "n_heldout"]))
    else:
        _write_csv(folder / "coverage.csv", [], _TABLE_COLUMNS)
        lines.append("Stage `calibration` not run.\n")

    lines.append(f"## {SUMMARY_SECTIONS[4]}\n")
    if trend:
        _write_csv(folder / "trend.csv", [dict(trend)])
        lines.append(f"Spearman ρ between the true γ and the stack γ_MLE of the EPL test sets: "
                     f"ρ = {_fmt(trend.get('rho'))} (p = {float(trend.get('p_value', float('nan'))):.3g}, "
                     f"{int(trend.get('n', 0))} sets).\n")
    else:
        _write_csv(folder / "trend.csv", [], ["rho", "p_value", "n"])
        lines.append("Not computed (calibration or figures stage off).\n")

    lines.append(f"## {SUMMARY_SECTIONS[5]}\n")
    rows = read_benchmarks(benchmarks or {})
    _write_csv(folder / "stage_runtime.csv", rows, ["stage", "jobs", "seconds", "longest_job_s", "peak_rss_mb"])
    lines.append("Summed job wall time per stage (Snakemake benchmark files; jobs run in parallel, so the sum "
                 "exceeds the wall time of the run):\n")
    lines.append(_md_table(rows, ["stage", "jobs", "seconds", "longest_job_s", "peak_rss_mb"]))
    return _write_text(out_md, "\n".join(lines))
