"""Empirical calibration of the interval threshold and its coverage (docs/estimator.md).

A trained ratio estimator is not a perfect likelihood, so ``t(γ_true)`` need not follow
Wilks' χ²₁. For each stack size N the threshold τ_N is therefore the empirical
``level``-quantile of ``t(γ_true)`` over many simulated stacks with known γ
(:func:`threshold`); the interval of a new stack is ``{γ : t(γ) ≤ τ_N}``
(:func:`subslope.stats.intervals.interval`). Whether this works is checked on held-out stacks
that did not set the threshold (:func:`split`, :func:`coverage`,
:func:`expected_coverage`), in the spirit of lampe's ``expected_coverage`` and sbi's
SBC: plain functions over (γ*, x*) pairs that return ``(levels, coverages)``.

Quantile definition (:func:`threshold`): the split-conformal order statistic
``τ = t_(k)``, ``k = ⌈(n + 1)·level⌉`` of the sorted sample. For a new stack exchangeable
with the ``n`` calibration stacks this guarantees ``P(t_new ≤ τ) ≥ level`` (and
``≤ level + 1/(n+1)`` without ties): slightly conservative, never optimistic.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from subslope.stats.intervals import stack as _stack
from subslope.stats.intervals import t_at

__all__ = [
    "FewSamplesWarning",
    "Stacks",
    "CALIBRATION_COLUMNS",
    "calibrate",
    "calibration_table",
    "safe_threshold",
    "coverage",
    "coverage_sigma",
    "expected_coverage",
    "STACK_MODES",
    "make_stacks",
    "overconfident",
    "split",
    "stack_t_true",
    "threshold",
    "thresholds",
    "wilks_coverage",
    "wilks_threshold",
]

#: Below this many samples :func:`threshold` warns (the 68% quantile is then uncertain
#: by more than ~±0.07 in probability).
MIN_SAMPLES = 50


class FewSamplesWarning(UserWarning):
    """Too few samples for a reliable empirical quantile or coverage."""


def _check_t(t, name="t_true") -> np.ndarray:
    a = np.asarray(t, dtype=np.float64).ravel()
    if a.size == 0:
        raise ValueError(f"{name} is empty")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds non-finite values")
    if np.any(a < 0):
        raise ValueError(f"{name} must be >= 0 (test statistics), got min {a.min()!r}")
    return a


def _check_level(level, name="level") -> float:
    lv = float(level)
    if not (0.0 < lv < 1.0):
        raise ValueError(f"{name} must lie in (0, 1), got {level!r}")
    return lv


def thresholds(t_true, levels) -> np.ndarray:
    """Conformal thresholds for several levels at once (see :func:`threshold`).

    Levels whose order statistic would be beyond the sample (``⌈(n+1)α⌉ > n``) give
    ``+inf`` (every γ is in the interval: the sample is too small for that level).
    """
    a = np.sort(_check_t(t_true))
    lv = np.asarray(levels, dtype=np.float64)
    if np.any(~((lv > 0) & (lv < 1))):
        raise ValueError("levels must lie in (0, 1)")
    n = a.size
    k = np.ceil((n + 1) * lv - 1e-9).astype(int)  # 1-based rank; guard round-off at exact multiples
    k = np.maximum(k, 1)
    out = np.full(lv.shape, np.inf)
    ok = k <= n
    out[ok] = a[k[ok] - 1]
    return out


def threshold(t_true, level: float = 0.68) -> float:
    """Empirical threshold τ: the conformal ``level``-quantile of ``t(γ_true)``.

    ``τ = t_(k)`` with ``k = ⌈(n+1)·level⌉`` (1-based rank in the sorted sample of ``n``
    values): the smallest order statistic that guarantees coverage ≥ ``level`` for a new
    exchangeable stack. For n = 20,000 it differs from ``np.quantile(..., 'higher')`` by
    at most one rank. Warns (:class:`FewSamplesWarning`) below 50 samples; raises
    ``ValueError`` when the sample is too small for the level (``k > n``).
    """
    a = _check_t(t_true)
    lv = _check_level(level)
    if a.size < MIN_SAMPLES:
        warnings.warn(
            f"threshold: only {a.size} samples of t(γ_true) (< {MIN_SAMPLES}); the {lv:.0%} "
            "quantile is "
            "poorly determined",
            FewSamplesWarning,
            stacklevel=2,
        )
    tau = float(thresholds(a, [lv])[0])
    if not math.isfinite(tau):
        raise ValueError(
            f"threshold: {a.size} samples are too few for level {lv} (need ⌈(n+1)·level⌉ <= n)"
        )
    return tau


def wilks_threshold(level: float = 0.68, dof: int = 1) -> float:
    """Wilks' asymptotic threshold ``χ²_dof.ppf(level)`` (0.989 for 68%, one parameter)."""
    return float(stats.chi2.ppf(_check_level(level), dof))


# ---------------------------------------------------------------------------------------
# stacks
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stacks:
    """Stacks of ``n`` images: ``indices (S, n)`` rows of the image table, the shared
    true ``gamma (S,)`` and the ``set_id (S,)`` each stack was drawn from."""

    indices: np.ndarray
    gamma: np.ndarray
    set_id: np.ndarray

    def __len__(self) -> int:
        return len(self.indices)


def _rng(rng):
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


#: How :func:`make_stacks` cuts the sets into stacks.
STACK_MODES = ("independent", "disjoint")


def _first_of_each_set(g, ids, members, eligible, n: int, n_stacks) -> Stacks:
    """One stack per set: its first ``n`` rows (``mode="independent"`` of make_stacks)."""
    if n_stacks is not None:
        raise ValueError("n_stacks applies to mode='disjoint' only")
    rows = np.asarray([np.sort(members[k])[:n] for k in eligible], dtype=np.int64)
    return Stacks(indices=rows, gamma=g[rows[:, 0]], set_id=ids[np.asarray(eligible)])


def make_stacks(
    gamma_true,
    set_index,
    n: int,
    rng=None,
    n_stacks: int | None = None,
    *,
    mode: str = "disjoint",
) -> Stacks:
    """Stacks of ``n`` distinct images of one set (all sharing the set's true γ).

    ``mode="independent"``: one stack per set, its first ``n`` images in file order (no
    ``rng`` needed). Stacks then share neither an image nor a γ draw, so every stack is
    an independent trial and binomial coverage errors are honest; it needs as many sets
    as stacks. ``mode="disjoint"`` (the default) cuts every set into several stacks, as
    below: more stacks from few sets, but stacks of one set share their γ.

    ``gamma_true (M,)``, ``set_index (M,)``: per image, its true γ and the id of its set
    (the simulation writes sets of 13 images with a shared γ). Sets with fewer than ``n``
    images are skipped. ``rng``: a ``numpy.random.Generator`` or a seed.

    - ``n_stacks=None`` (default): every set is shuffled and cut into ``⌊size/n⌋``
      disjoint stacks. No image is used twice anywhere, so the stacks are independent
      (use this for calibration and coverage: binomial errors are then valid).
    - ``n_stacks=k``: exactly ``k`` stacks. The disjoint ones above are used first (a
      random subset of them if ``k`` is smaller); beyond them, further stacks are drawn
      as random ``n``-subsets of randomly chosen sets. An image is never repeated within
      a stack, but stacks then share images and are correlated.

    Raises ``ValueError`` when a set mixes different true γ or no set has ``n`` images.
    """
    g = np.asarray(gamma_true, dtype=np.float64)
    sid = np.asarray(set_index)
    if g.ndim != 1 or sid.shape != g.shape:
        raise ValueError(
            f"gamma_true and set_index must be 1-D of equal length, got {g.shape} and {sid.shape}"
        )
    if int(n) != n or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    n = int(n)
    gen = _rng(rng)
    ids, inv = np.unique(sid, return_inverse=True)
    members = [np.flatnonzero(inv == k) for k in range(ids.size)]
    for k, m in enumerate(members):
        if np.ptp(g[m]) > 1e-9 * max(1.0, abs(g[m[0]])):
            raise ValueError(
                f"make_stacks: set {ids[k]!r} mixes true γ values {np.unique(g[m])[:5]}"
            )
    eligible = [k for k, m in enumerate(members) if m.size >= n]
    if not eligible:
        raise ValueError(
            f"make_stacks: no set has >= n = {n} images (largest: {max(m.size for m in members)})"
        )
    if mode not in STACK_MODES:
        raise ValueError(f"mode must be one of {STACK_MODES}, got {mode!r}")
    if mode == "independent":
        return _first_of_each_set(g, ids, members, eligible, n, n_stacks)
    rows, sets = [], []
    for k in eligible:
        perm = gen.permutation(members[k])
        for s in range(members[k].size // n):
            rows.append(perm[s * n : (s + 1) * n])
            sets.append(k)
    rows_a = np.asarray(rows, dtype=np.int64).reshape(-1, n)
    sets_a = np.asarray(sets, dtype=np.int64)
    if n_stacks is not None:
        if int(n_stacks) != n_stacks or n_stacks < 1:
            raise ValueError(f"n_stacks must be a positive integer or None, got {n_stacks!r}")
        k_total = int(n_stacks)
        if k_total <= len(rows_a):
            pick = np.sort(gen.choice(len(rows_a), size=k_total, replace=False))
            rows_a, sets_a = rows_a[pick], sets_a[pick]
        else:
            extra_sets = gen.choice(eligible, size=k_total - len(rows_a))
            extra = np.stack([gen.choice(members[k], size=n, replace=False) for k in extra_sets])
            rows_a = np.concatenate([rows_a, extra])
            sets_a = np.concatenate([sets_a, extra_sets])
    return Stacks(indices=rows_a, gamma=g[rows_a[:, 0]], set_id=ids[sets_a])


def stack_t_true(profiles, gammas, stacks: Stacks) -> np.ndarray:
    """``t(γ_true)`` of every stack: stack the image profiles ``(B, G)`` then :func:`t_at`."""
    return np.asarray(
        t_at(_stack(profiles, stacks.indices), gammas, stacks.gamma), dtype=np.float64
    )


def split(keys, *, seed: int = 0, fraction: float = 0.5) -> np.ndarray:
    """Deterministic calibration / held-out split: boolean mask, True = calibration.

    The distinct ``keys`` (e.g. ``Stacks.set_id``, so that stacks drawn from the same set
    never end up on both sides) are permuted with ``default_rng(seed)``; the first
    ``round(fraction · n_keys)`` keys are calibration, the rest held out. For independent
    stacks pass ``np.arange(S)``.
    """
    k = np.asarray(keys)
    if k.ndim != 1 or k.size == 0:
        raise ValueError(f"keys must be a non-empty 1-D array, got shape {k.shape}")
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must lie in (0, 1), got {fraction!r}")
    uniq, inv = np.unique(k, return_inverse=True)
    if uniq.size < 2:
        raise ValueError("split: need at least 2 distinct keys")
    order = np.random.default_rng(seed).permutation(uniq.size)
    n_cal = min(max(int(round(fraction * uniq.size)), 1), uniq.size - 1)
    is_cal_key = np.zeros(uniq.size, dtype=bool)
    is_cal_key[order[:n_cal]] = True
    return is_cal_key[inv]


# ---------------------------------------------------------------------------------------
# coverage
# ---------------------------------------------------------------------------------------
def coverage(
    t_true, threshold: float, *, wilson_level: float = 0.68
) -> tuple[float, float, tuple[float, float]]:
    """Observed coverage of intervals ``{t ≤ threshold}``.

    Returns ``(fraction, binomial standard error √(p(1−p)/n), Wilson score interval at
    wilson_level)``; the Wilson interval stays inside [0, 1] and is sensible at p = 0 or 1.
    Warns below 50 samples.
    """
    a = _check_t(t_true)
    n = a.size
    if n < MIN_SAMPLES:
        warnings.warn(
            f"coverage: only {n} samples (< {MIN_SAMPLES})", FewSamplesWarning, stacklevel=2
        )
    p = float(np.mean(a <= float(threshold)))
    se = math.sqrt(p * (1 - p) / n)
    z = float(stats.norm.ppf(0.5 + _check_level(wilson_level, "wilson_level") / 2))
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return p, se, (max(0.0, centre - half), min(1.0, centre + half))


def coverage_sigma(level, n_calibration, n_heldout):
    """Standard deviation of the held-out coverage of a split-conformal threshold when the
    estimator's calibration is exact.

    Two independent samples make it scatter: the threshold, set by ``n_calibration``
    stacks, covers a fraction ``F(τ)`` of new stacks that is Beta-distributed with
    variance ``α(1−α)/(n_calibration + 2)`` (``α`` the level; the conformal rank
    statistic), and the ``n_heldout`` stacks that measure it add the binomial
    ``α(1−α)/n_heldout``. Testing the held-out coverage against the level with the
    binomial error alone ignores the first term, which is as large as the second for an
    even split.
    """
    lv = np.asarray(level, dtype=np.float64)
    n_c = np.asarray(n_calibration, dtype=np.float64)
    n_h = np.asarray(n_heldout, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(lv * (1 - lv) * (1 / n_h + 1 / (n_c + 2)))


def overconfident(coverage, sigma, level):
    """Held-out coverage more than 2σ below the credibility level; ``σ`` the scatter of
    the held-out coverage (:func:`coverage_sigma`)."""
    return np.asarray(coverage) < np.asarray(level) - 2 * np.asarray(sigma)


def _levels(levels) -> np.ndarray:
    lv = np.linspace(0.01, 0.99, 99) if levels is None else np.asarray(levels, dtype=np.float64)
    if lv.ndim != 1 or lv.size == 0 or np.any(~((lv > 0) & (lv < 1))):
        raise ValueError("levels must be a non-empty 1-D array in (0, 1)")
    return lv


def expected_coverage(t_calibration, t_heldout, levels=None) -> tuple[np.ndarray, np.ndarray]:
    """Expected-coverage curve of the empirical calibration: ``(levels, coverages)``.

    For each credibility level α, the fraction of held-out stacks with
    ``t(γ_true) ≤ τ_α``, τ_α the conformal α-quantile (:func:`thresholds`) of the
    calibration stacks. A calibrated procedure follows the diagonal. ``levels`` default:
    0.01, 0.02, …, 0.99. The two samples must not overlap (use :func:`split`).
    """
    lv = _levels(levels)
    cal, held = _check_t(t_calibration, "t_calibration"), _check_t(t_heldout, "t_heldout")
    if min(cal.size, held.size) < MIN_SAMPLES:
        warnings.warn(
            f"expected_coverage: {cal.size} calibration / {held.size} held-out samples (< "
            f"{MIN_SAMPLES})",
            FewSamplesWarning,
            stacklevel=2,
        )
    tau = thresholds(cal, lv)
    return lv, np.mean(held[None, :] <= tau[:, None], axis=1)


def wilks_coverage(t_heldout, levels=None, dof: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Expected-coverage curve with Wilks thresholds ``χ²_dof.ppf(α)``: ``(levels, coverages)``."""
    lv = _levels(levels)
    held = _check_t(t_heldout, "t_heldout")
    tau = stats.chi2.ppf(lv, dof)
    return lv, np.mean(held[None, :] <= tau[:, None], axis=1)


def safe_threshold(t, level: float) -> tuple[float, bool]:
    """``(τ, exact)``: the conformal threshold of :func:`threshold`, or, when the sample is
    too small for that level (rank ⌈(n+1)α⌉ > n), the largest ``t`` with ``exact=False``
    (tiny test campaigns); NaN for an empty sample."""
    t = np.asarray(t, dtype=np.float64)
    if t.size == 0:
        return float("nan"), False
    if math.ceil((t.size + 1) * level) > t.size:
        return float(np.max(t)), False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FewSamplesWarning)
        return float(threshold(t, level)), True


#: The scalar columns of :func:`calibrate`, in the order of the calibration table.
CALIBRATION_COLUMNS = (
    "tau",
    "tau_exact",
    "tau_wilks",
    "tau_calibration",
    "n_calibration",
    "n_heldout",
    "coverage",
    "coverage_err",
    "wilson_lo",
    "wilson_hi",
    "coverage_wilks",
    "coverage_wilks_err",
)


def calibrate(
    t_true, keys, *, level: float = 0.68, seed: int = 0, fraction: float = 0.5, levels=None
) -> dict[str, Any]:
    """The threshold of one stack size and its held-out coverage.

    ``t_true``: ``t(γ_true)`` of the stacks; ``keys``: their split keys (e.g.
    ``Stacks.set_id``), of which :func:`split` puts ``fraction`` in the calibration part
    (all of them when there is a single key). Returns:

    - ``tau``: the threshold from *all* stacks (:func:`safe_threshold`; the one to apply
      to new data, e.g. the HST stack), ``tau_exact`` whether the sample reached its rank;
      ``tau_wilks``: Wilks' χ²₁ threshold (0.989 at 68%);
    - ``tau_calibration``: the threshold from the calibration part; ``n_calibration``,
      ``n_heldout``, ``is_calibration`` (per stack);
    - ``coverage``, ``coverage_err`` (binomial σ), ``wilson_lo``, ``wilson_hi``: the
      held-out coverage at ``tau_calibration``; ``coverage_wilks``, ``coverage_wilks_err``
      the same at ``tau_wilks`` (NaN without held-out stacks);
    - ``levels``, ``coverage_curve``, ``coverage_curve_wilks``: expected-coverage curves
      over ``levels`` (default 0.01…0.99) with thresholds from the calibration part.
    """
    t = _check_t(t_true)
    keys = np.asarray(keys)
    if keys.shape != t.shape:
        raise ValueError(f"keys must have one key per stack ({t.size}), got shape {keys.shape}")
    lv = _levels(levels)
    tau, exact = safe_threshold(t, level)
    tau_w = wilks_threshold(level)
    try:
        is_cal = split(keys, seed=seed, fraction=fraction)
    except ValueError:  # a single key: nothing to hold out
        is_cal = np.ones(t.size, dtype=bool)
    t_cal, t_held = t[is_cal], t[~is_cal]
    tau_cal, _ = safe_threshold(t_cal, level)
    out = dict(
        tau=tau,
        tau_exact=bool(exact),
        tau_wilks=tau_w,
        tau_calibration=tau_cal,
        n_calibration=int(is_cal.sum()),
        n_heldout=int((~is_cal).sum()),
        is_calibration=is_cal,
        levels=lv,
    )
    nan = float("nan")
    out.update(
        coverage=nan,
        coverage_err=nan,
        wilson_lo=nan,
        wilson_hi=nan,
        coverage_wilks=nan,
        coverage_wilks_err=nan,
        coverage_curve=np.full(lv.size, np.nan),
        coverage_curve_wilks=np.full(lv.size, np.nan),
    )
    if not t_held.size:
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FewSamplesWarning)
        p, err, (wlo, whi) = coverage(t_held, tau_cal)
        pw, errw, _ = coverage(t_held, tau_w)
        _, curve_w = wilks_coverage(t_held, lv)
    curve = np.array([np.mean(t_held <= safe_threshold(t_cal, a)[0]) for a in lv])
    out.update(
        coverage=p,
        coverage_err=err,
        wilson_lo=wlo,
        wilson_hi=whi,
        coverage_wilks=pw,
        coverage_wilks_err=errw,
        coverage_curve=curve,
        coverage_curve_wilks=curve_w,
    )
    return out


def calibration_table(
    t_by_n: Mapping[int, np.ndarray],
    keys_by_n: Mapping[int, np.ndarray] | None = None,
    *,
    level: float = 0.68,
    seed: int = 0,
    fraction: float = 0.5,
):
    """Per-N calibration summary as a pandas DataFrame (one row per N, sorted): the
    columns ``n_images``, :data:`CALIBRATION_COLUMNS` and ``level``, each row
    :func:`calibrate` of ``t_by_n[N]`` (``t(γ_true)`` of the stacks of N images) split by
    ``keys_by_n[N]`` (default: each stack its own key). Warns for N with fewer than
    ``2 × MIN_SAMPLES`` stacks."""
    import pandas as pd

    lv = _check_level(level)
    rows = []
    for n in sorted(t_by_n):
        t = _check_t(t_by_n[n], f"t_by_n[{n}]")
        keys = np.arange(t.size) if keys_by_n is None else np.asarray(keys_by_n[n])
        if keys.shape != t.shape:
            raise ValueError(
                f"keys_by_n[{n}] must have one key per stack ({t.size}), got shape {keys.shape}"
            )
        if t.size < 2 * MIN_SAMPLES:
            warnings.warn(
                f"calibration_table: N={n} has only {t.size} stacks",
                FewSamplesWarning,
                stacklevel=2,
            )
        cal = calibrate(t, keys, level=lv, seed=seed, fraction=fraction, levels=[lv])
        rows.append(dict(n_images=int(n), **{c: cal[c] for c in CALIBRATION_COLUMNS}, level=lv))
    return pd.DataFrame(rows)
