"""Stage ``null_tests``, halo-free part: the null test a γ-blind estimator must pass,
and the bias of γ_MLE against the number of subhalos (rule halo_free_null; docs/inference.md).

A substructure-free image need not give a flat profile: under the training prior an
image without visible perturbations is likelier at low γ, so the Bayes-optimal profile
of such an image slopes. What must hold instead is that γ reaches the estimator only
through the halos. Test images are re-rendered from their stored parameters with every
subhalo and line-of-sight halo removed — once with the halos' negative sheets kept
(``sheets_kept``), once with them removed too (``sheets_removed``) — with the shard's
lens, source, lens light, sky and noise seeds
(:func:`subslope.simulation.rerender.halo_free_images`). Their γ_MLE must not correlate
with the label the original images carried: Spearman ρ of the single-image and of the
stack γ_MLE within 2σ of 0 (σ = 1/√(n − 1)), and the least-squares slope of the stack
γ_MLE on the label within 2 standard errors of 0. A correlation means γ reaches the
estimator through something else (the sheets, the placement mask, the macro draw). The
original images (``original``) are reported beside them, and the bias γ_MLE − γ of the
originals in bins of N_sub (the paper's Fig. 4 question: do images with few subhalos
pull towards the prior?).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from subslope.io.atomic import write_text
from subslope.io.shards import open_shard
from subslope.stats import intervals

__all__ = [
    "VARIANTS",
    "RERENDERS",
    "HALO_FREE_COLUMNS",
    "BIAS_COLUMNS",
    "SHEET_COLUMNS",
    "label_trend",
    "partial_spearman",
    "sheet_channel",
    "nsub_bias",
    "variant_row",
    "halo_free_shard",
    "halo_free_null",
    "halo_free_verdict",
]

log = logging.getLogger(__name__)

#: Shard parameters a halo-free profiles file needs.
_PARAMS = ("theta_e", "lens_x", "lens_y", "gamma_sub", "set_index", "c_multiplier")

#: The images compared: as stored, halos removed with their sheets kept, and removed too.
VARIANTS = ("original", "sheets_kept", "sheets_removed")
#: Re-renders :func:`halo_free_shard` makes: the test's two, and the subhalos alone
#: removed (line-of-sight halos kept; :mod:`subslope.stages.null_tests.visibility`).
RERENDERS = (*VARIANTS[1:], "subhalos_removed")
#: Columns of ``halo_free.csv``, one row per variant.
HALO_FREE_COLUMNS = (
    "variant",
    "n_images",
    "n_stacks",
    "rho_single",
    "rho_single_p",
    "rho_stack",
    "rho_stack_p",
    "slope_stack",
    "slope_stack_se",
    "stack_mle_p50",
    "passes",
)
#: Columns of ``nsub_bias.csv``, one row per N_sub bin of the original images.
BIAS_COLUMNS = (
    "n_sub_lo",
    "n_sub_hi",
    "n_images",
    "bias_mean",
    "bias_mean_se",
    "bias_p16",
    "bias_p50",
    "bias_p84",
)


#: Columns of ``sheet_channel.csv``: how the kept sheets carry γ (:func:`sheet_channel`).
SHEET_COLUMNS = ("quantity", "against", "given", "n_stacks", "rho", "p", "bound", "within")


def _normal_scores(v) -> np.ndarray:
    from scipy.stats import norm, rankdata

    r = rankdata(v)
    return norm.ppf((r - 0.5) / r.size)


def partial_spearman(x, y, given) -> float:
    """Rank correlation of ``x`` and ``y`` with the variables ``given`` (a sequence of
    arrays) held fixed: the normal scores of ``x`` and ``y`` (ranks mapped through the
    inverse normal CDF) are fitted by least squares on a cubic in the normal scores of
    each given variable and their pairwise products, and the residuals correlated. The
    cubic and the products take out monotone, curved and joint dependences on the given
    variables that a straight line in their ranks would leave behind. 0 when a residual
    is constant."""
    scores = [_normal_scores(v) for v in given]
    cols = [np.ones(len(x))] + [s**p for s in scores for p in (1, 2, 3)]
    cols += [a * b for k, a in enumerate(scores) for b in scores[k + 1 :]]
    design = np.column_stack(cols)
    res = []
    for v in (x, y):
        r = _normal_scores(v)
        coef, *_ = np.linalg.lstsq(design, r, rcond=None)
        res.append(r - design @ coef)
    den = math.sqrt(float(np.sum(res[0] ** 2) * np.sum(res[1] ** 2)))
    return float(np.sum(res[0] * res[1]) / den) if den > 1e-9 * len(x) else 0.0


def sheet_channel(label, sheets: Mapping[str, np.ndarray], kept_mle) -> list[dict[str, Any]]:
    """Rows :data:`SHEET_COLUMNS` for stacks with labels ``label``, the stack-mean κ of
    their images' negative sheets ``sheets`` (``{"subhalos": ..., "los": ...}``) and the
    γ_MLE of their sheets-kept re-renders ``kept_mle``: does each sheet follow the label,
    does the kept-sheet γ_MLE follow each sheet, and does anything of the label remain in
    it with the sheets held fixed (:func:`partial_spearman`, bound 2/√(n − 1 − m) for the
    m regressors of the fit)?
    ``within`` says whether |ρ| is inside the bound of no correlation. A sheet that is
    zero everywhere (a scene without that population) is left out."""
    from scipy.stats import spearmanr

    label, mle = np.asarray(label, float), np.asarray(kept_mle, float)
    sheets = {f"sheet_kappa_{k}": np.asarray(v, float) for k, v in sheets.items() if np.ptp(v)}
    n = label.size
    rows = []

    def row(quantity, against, given, rho, p, bound):
        return dict(quantity=quantity, against=against, given=given, n_stacks=n, rho=rho) | dict(
            p=p, bound=bound, within=bool(abs(rho) <= bound)
        )

    pairs = [(k, "label", v, label) for k, v in sheets.items()]
    pairs += [("sheets_kept_mle", k, mle, v) for k, v in sheets.items()]
    for quantity, against, x, y in pairs:
        rho, p = (0.0, 1.0) if np.ptp(x) == 0 or np.ptp(y) == 0 else spearmanr(x, y)
        rows.append(row(quantity, against, "", float(rho), float(p), 2.0 / math.sqrt(n - 1)))
    k = len(sheets)
    dof = n - 1 - 3 * k - k * (k - 1) // 2
    if sheets and dof >= 1:  # fewer stacks than the fit's regressors: no partial test
        rho = partial_spearman(mle, label, list(sheets.values()))
        bound = 2.0 / math.sqrt(dof)
        rows.append(row("sheets_kept_mle", "label", " + ".join(sheets), rho, math.nan, bound))
    return rows


def label_trend(labels, mle) -> dict[str, float]:
    """Spearman ρ (and p) of ``mle`` against ``labels``, its 2σ bound under no
    correlation (2/√(n − 1)), and the least-squares slope of ``mle`` on ``labels`` with
    its standard error. A constant ``mle`` (every value at a prior edge, say) has ρ = 0,
    p = 1: nothing of the label is in it."""
    from scipy.stats import spearmanr

    x, y = np.asarray(labels, float), np.asarray(mle, float)
    n = x.size
    if n < 3:
        raise ValueError(f"a label trend needs at least 3 values, got {n}")
    if np.ptp(y) == 0 or np.ptp(x) == 0:
        rho, p = 0.0, 1.0
    else:
        rho, p = (float(v) for v in spearmanr(x, y))
    xc = x - x.mean()
    slope = float(np.sum(xc * (y - y.mean())) / np.sum(xc**2)) if np.ptp(x) else 0.0
    resid = y - y.mean() - slope * xc
    se = float(np.sqrt(np.sum(resid**2) / (n - 2) / np.sum(xc**2))) if np.ptp(x) else math.inf
    return {"rho": rho, "p": p, "bound": 2.0 / math.sqrt(n - 1), "slope": slope, "se": se}


def nsub_bias(n_sub, gamma_true, mle, n_bins: int = 5) -> list[dict[str, Any]]:
    """Rows :data:`BIAS_COLUMNS`: γ_MLE − γ in ``n_bins`` bins of N_sub with about equal
    numbers of images (edges at quantiles of N_sub, integer, lower edge inclusive)."""
    n_sub = np.asarray(n_sub, dtype=np.int64)
    bias = np.asarray(mle, float) - np.asarray(gamma_true, float)
    edges = np.unique(np.quantile(n_sub, np.linspace(0, 1, n_bins + 1)).round().astype(np.int64))
    edges[-1] = n_sub.max() + 1
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        b = bias[(n_sub >= lo) & (n_sub < hi)]
        if b.size == 0:
            continue
        p16, p50, p84 = np.percentile(b, [16, 50, 84])
        rows.append(
            {
                "n_sub_lo": int(lo),
                "n_sub_hi": int(hi - 1),
                "n_images": int(b.size),
                "bias_mean": float(b.mean()),
                "bias_mean_se": float(b.std(ddof=1) / math.sqrt(b.size))
                if b.size > 1
                else math.nan,
                "bias_p16": float(p16),
                "bias_p50": float(p50),
                "bias_p84": float(p84),
            }
        )
    return rows


def variant_row(variant: str, gammas, prof, gamma_true, set_id) -> dict[str, Any]:
    """One row of :data:`HALO_FREE_COLUMNS`: the label trend of the single-image and the
    stack γ_MLE of profiles ``prof (B, G)`` (stacks: the images of each ``set_id``) and
    the verdict (blank for the original images, which are not tested)."""
    single = np.atleast_1d(intervals.mle(prof, gammas))
    ids, inv = np.unique(set_id, return_inverse=True)
    stacked = intervals.stack(prof, inv)
    stack_mle = np.atleast_1d(intervals.mle(stacked, gammas))
    first = np.array([np.flatnonzero(inv == k)[0] for k in range(ids.size)])
    t1, ts = label_trend(gamma_true, single), label_trend(gamma_true[first], stack_mle)
    passes = (
        abs(t1["rho"]) <= t1["bound"]
        and abs(ts["rho"]) <= ts["bound"]
        and abs(ts["slope"]) <= 2 * ts["se"]
    )
    return {
        "variant": variant,
        "n_images": int(prof.shape[0]),
        "n_stacks": int(ids.size),
        "rho_single": t1["rho"],
        "rho_single_p": t1["p"],
        "rho_stack": ts["rho"],
        "rho_stack_p": ts["p"],
        "slope_stack": ts["slope"],
        "slope_stack_se": ts["se"],
        "stack_mle_p50": float(np.median(stack_mle)),
        "passes": bool(passes) if variant != "original" else "",
    }


def halo_free_shard(
    config: Mapping[str, Any],
    model_path,
    shard_path,
    out_paths: Mapping[str, Any],
    *,
    gammas,
    batch_size: int = 64,
    device: str = "auto",
    run_name: str = "",
) -> dict[str, Path]:
    """Profiles files (:func:`subslope.io.ratio_profiles.write_profiles`) of every image
    of one shard re-rendered without halos, one per variant of ``out_paths``
    (:data:`RERENDERS`: ``sheets_kept``, ``sheets_removed``, ``subhalos_removed``). A
    lens-light-subtracting estimator gets the fitted light of the re-rendered images
    (the stored fit is of the originals)."""
    from subslope.io.ratio_profiles import write_profiles
    from subslope.nre.evaluate import estimator_profiles
    from subslope.nre.inputs import InputTransform
    from subslope.nre.train import load_estimator
    from subslope.simulation.observing import fitted_light_models
    from subslope.simulation.rerender import halo_free_images, subhalo_free_images
    from subslope.simulation.sources import cosmos_folders

    cosmos = [str(f) for f in cosmos_folders(config)]  # this campaign's, wherever it runs
    unknown = set(out_paths) - set(RERENDERS)
    if unknown:
        raise ValueError(f"halo-free variants {sorted(unknown)}: allowed {list(RERENDERS)}")
    model, meta = load_estimator(model_path)
    needs_light = InputTransform.from_json(meta.get("inputs")).needs_light
    with open_shard(shard_path) as s:
        par = {k: s.params.get(k) for k in _PARAMS}  # CDM shards: no γ; EPL: no multiplier
        par = {k: None if v is None else np.asarray(v) for k, v in par.items()}
        psf = np.asarray(s.psf)
        n = int(s.images.shape[0])
    written = {}
    for variant, out in out_paths.items():
        images = (
            subhalo_free_images(shard_path, np.arange(n), cosmos=cosmos)
            if variant == "subhalos_removed"
            else halo_free_images(
                shard_path, np.arange(n), keep_sheets=variant == "sheets_kept", cosmos=cosmos
            )
        )
        light = fitted_light_models(config, images, par["theta_e"], psf)[1] if needs_light else None
        prof = estimator_profiles(
            model,
            meta,
            images,
            par["theta_e"],
            par["lens_x"],
            par["lens_y"],
            gammas,
            batch_size=batch_size,
            device=device,
            light=light,
        )
        attrs = {
            "scene": f"halo_free/{variant}",
            "shard": os.fspath(shard_path),
            "model": os.fspath(model_path),
            "model_config_hash": str(meta.get("config_hash", "")),
            "run_name": run_name,
        }
        written[variant] = write_profiles(
            out,
            log_ratio=prof,
            gammas=gammas,
            gamma_true=par["gamma_sub"],
            set_index=par["set_index"],
            c_multiplier=par["c_multiplier"],
            theta_e=par["theta_e"],
            lens_x=par["lens_x"],
            lens_y=par["lens_y"],
            attrs=attrs,
        )
    return written


def _first_sets(profiles: Mapping[str, np.ndarray], n_sets: int, what: str):
    """The rows of the first ``n_sets`` sets (sets in file order)."""
    have = int(np.unique(profiles["set_id"]).size)
    if have < n_sets:
        raise ValueError(
            f"null_tests.halo_free_sets = {n_sets}: the {what} profiles hold only {have} sets"
        )
    return profiles["set_id"] < n_sets


def halo_free_null(
    original: Sequence,
    variants: Mapping[str, Sequence],
    shard_paths: Sequence,
    out_csv,
    bias_csv,
    sheet_csv=None,
    *,
    n_sets: int,
):
    """``halo_free.csv`` (:data:`HALO_FREE_COLUMNS`, one row per variant) and
    ``nsub_bias.csv`` (:data:`BIAS_COLUMNS`) of the first ``n_sets`` sets: the profiles
    files of the stored test images (``original``), of the same shards halo-free
    (``variants``: variant -> files, :func:`halo_free_shard`), and the shards themselves
    (their N_sub), all in the same shard order. ``sheet_csv``: also
    ``sheet_channel.csv`` (:func:`sheet_channel`), with the sheet κ of every tested image
    computed from the shards (:func:`subslope.simulation.rerender.sheet_kappas`)."""
    import pandas as pd

    from subslope.io.ratio_profiles import read_profiles

    orig = read_profiles(original)
    keep = _first_sets(orig, n_sets, "original")
    per_shard = [_shard_column(p, "n_sub") for p in shard_paths]
    n_sub = np.concatenate(per_shard)
    if n_sub.size != keep.size:
        raise ValueError(f"the test shards hold {n_sub.size} images, their profiles {keep.size}")
    g = orig["gammas"]
    label, set_id = orig["gamma_true"][keep], orig["set_id"][keep]
    rows = [variant_row("original", g, orig["log_ratio"][keep], label, set_id)]
    tested = {}
    for variant in VARIANTS[1:]:
        prof = read_profiles(variants[variant])
        sel = _first_sets(prof, n_sets, variant)
        if not np.array_equal(prof["gamma_true"][sel], label):
            raise ValueError(f"{variant}: the halo-free profiles are not of the original images")
        tested[variant] = prof["log_ratio"][sel]
        rows.append(variant_row(variant, g, tested[variant], label, set_id))
    table = pd.DataFrame(rows, columns=HALO_FREE_COLUMNS)
    write_text(out_csv, table.to_csv(index=False))
    single = np.atleast_1d(intervals.mle(orig["log_ratio"][keep], g))
    bias = pd.DataFrame(nsub_bias(n_sub[keep], label, single), columns=BIAS_COLUMNS)
    write_text(bias_csv, bias.to_csv(index=False))
    log.info("halo-free null test:\n%s\nbias by N_sub:\n%s", table, bias)
    if sheet_csv is not None:
        kappas = _sheet_kappas(shard_paths, [c.size for c in per_shard], keep)
        ids, inv = np.unique(set_id, return_inverse=True)
        stack_mle = np.atleast_1d(intervals.mle(intervals.stack(tested["sheets_kept"], inv), g))
        first = np.array([np.flatnonzero(inv == k)[0] for k in range(ids.size)])
        stack_kappa = {k: np.bincount(inv, weights=v) / np.bincount(inv) for k, v in kappas.items()}
        sheet = pd.DataFrame(
            sheet_channel(label[first], stack_kappa, stack_mle), columns=SHEET_COLUMNS
        )
        write_text(sheet_csv, sheet.to_csv(index=False))
        log.info("the kept sheets as a channel of gamma:\n%s", sheet)
    return table, bias


def _sheet_kappas(
    shard_paths: Sequence, sizes: Sequence[int], keep: np.ndarray
) -> dict[str, np.ndarray]:
    """The subhalo and line-of-sight sheet κ of the images ``keep`` selects (a mask over
    the images of shards of ``sizes`` images, in shard order)."""
    from subslope.simulation.rerender import sheet_kappas

    out: dict[str, list] = {"subhalos": [], "los": []}
    start = 0
    for path, n in zip(shard_paths, sizes, strict=True):
        rows = np.flatnonzero(keep[start : start + n])
        start += n
        if rows.size:
            for k, v in sheet_kappas(path, rows).items():
                out[k].append(v)
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}


def _shard_column(path, key: str) -> np.ndarray:
    with open_shard(path) as s:
        return np.asarray(s.params[key])


def _truth(value: Any) -> bool:
    return str(value).strip().lower() == "true"


def halo_free_verdict(rows) -> dict[str, Any] | None:
    """The halo-free null test's one verdict, from the rows of ``halo_free.csv`` (dicts
    of a CSV reader or a DataFrame's records), used by the summary and the results page:

    - ``passes``: the ``sheets_removed`` variant passes (with the halos and their
      negative sheets removed the γ_MLE does not follow the label: γ reaches the
      estimator through the halos); the test's criterion;
    - ``sheets_carry``: the ``sheets_kept`` variant fails (with only the sheets left the
      γ_MLE still follows the label: the sheets, whose amplitude is a function of the
      members' γ, carry part of it); a finding about the channel, not a failure;
    - ``uninformative``: the original images' stack ρ lies within 2/√(n − 1) of 0.

    None without a ``sheets_removed`` row."""
    by = {str(r["variant"]): r for r in rows}
    if "sheets_removed" not in by:
        return None
    orig = by.get("original")
    uninformative = False
    if orig is not None and orig.get("n_stacks") not in (None, "") and orig.get("rho_stack"):
        n = max(int(float(orig["n_stacks"])) - 1, 1)
        uninformative = abs(float(orig["rho_stack"])) <= 2.0 / math.sqrt(n)
    kept = by.get("sheets_kept")
    return {
        "passes": _truth(by["sheets_removed"]["passes"]),
        "sheets_carry": kept is not None and not _truth(kept["passes"]),
        "kept_rho_stack": None if kept is None else float(kept["rho_stack"]),
        "uninformative": uninformative,
    }
