"""Likelihood-ratio profiles, stacking, MLE and confidence intervals for γ (docs/estimator.md).

Definitions (docs/inference.md has the full account):

- **profile**: ``ln r̂(x|γ_g)`` of one image on a linear grid ``γ_g`` (:func:`gamma_grid`),
  computed by :func:`subslope.nre.evaluate.log_ratio_profiles` with the trained estimator;
- **stack**: a set of N images sharing one γ; its profile is the sum of the N image
  profiles (:func:`stack`), i.e. the product of their likelihood ratios;
- **MLE**: the grid argmax refined by the vertex of the parabola through the three grid
  points around it (:func:`refine_max`, :func:`mle`);
- **test statistic**: ``t(γ) = 2 (ln r̂(γ_MLE) − ln r̂(γ))`` with the refined maximum
  (:func:`test_statistic`); between nodes ``t`` is linear, with the point ``(γ_MLE, 0)``
  inserted as an extra node (:func:`t_at`);
- **interval**: ``{γ : t(γ) ≤ τ}`` for a threshold τ (:func:`interval`), with edge and
  multimodality flags.

All functions are numpy, float64, and take the grid as a separate argument; none calls
the network.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

__all__ = [
    "Interval",
    "check_grid",
    "gamma_grid",
    "interval",
    "intervals",
    "mle",
    "refine_max",
    "stack",
    "t_at",
    "test_statistic",
]


# ---------------------------------------------------------------------------------------
# grid
# ---------------------------------------------------------------------------------------
def gamma_grid(low: float = 1.1, high: float = 2.9, n: int = 181) -> np.ndarray:
    """Linear γ grid ``np.linspace(low, high, n)`` (float64); the default has Δγ = 0.01.

    Raises ``ValueError`` unless ``low < high`` are finite and ``n ≥ 3`` (the MLE
    refinement needs three points).
    """
    low, high = float(low), float(high)
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"gamma_grid: need finite low < high, got low={low!r}, high={high!r}")
    if int(n) != n or n < 3:
        raise ValueError(f"gamma_grid: n must be an integer >= 3, got {n!r}")
    return np.linspace(low, high, int(n), dtype=np.float64)


def check_grid(gammas) -> np.ndarray:
    """``gammas`` as a float64 array, checked: 1-D, >= 3 finite, strictly increasing values."""
    g = np.asarray(gammas, dtype=np.float64)
    if g.ndim != 1 or g.size < 3:
        raise ValueError(f"gammas must be a 1-D grid of >= 3 values, got shape {g.shape}")
    if not np.all(np.isfinite(g)) or not np.all(np.diff(g) > 0):
        raise ValueError("gammas must be finite and strictly increasing")
    return g


def _check_profile(profile, g: np.ndarray, name: str = "profile") -> np.ndarray:
    p = np.asarray(profile, dtype=np.float64)
    if p.ndim < 1 or p.shape[-1] != g.size:
        raise ValueError(
            f"{name} must have shape (..., G) with G = len(gammas) = {g.size}, got {p.shape}"
        )
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} holds non-finite values (NaN or ±inf); profiles must be finite")
    return p


# ---------------------------------------------------------------------------------------
# stacking
# ---------------------------------------------------------------------------------------
def stack(profiles, groups=None) -> np.ndarray:
    """Stacked profiles: the sum of ``ln r̂`` over the images of each stack.

    - ``groups=None``: sum over the image axis ``-2``: ``(N, G) → (G,)`` (one stack of all
      images), ``(S, N, G) → (S, G)``.
    - ``groups`` a 2-D integer array ``(S, N)`` (e.g. ``Stacks.indices`` from
      :func:`subslope.stats.calibration.make_stacks`): rows of ``profiles (B, G)`` → ``(S, G)``.
    - ``groups`` a 1-D array of ``B`` labels: one stack per distinct label, in the order
      of ``np.unique(groups)`` → ``(n_labels, G)`` (stacks may have different sizes).
    """
    p = np.asarray(profiles, dtype=np.float64)
    if p.ndim < 2:
        raise ValueError(f"profiles must have shape (..., N, G), got {p.shape}")
    if groups is None:
        return p.sum(axis=-2)
    grp = np.asarray(groups)
    if p.ndim != 2:
        raise ValueError(f"with groups, profiles must have shape (B, G), got {p.shape}")
    if grp.ndim == 2:
        if not np.issubdtype(grp.dtype, np.integer):
            raise ValueError(f"groups (S, N) must be integer row indices, got dtype {grp.dtype}")
        if grp.size and (grp.min() < 0 or grp.max() >= len(p)):
            raise ValueError(
                f"groups: indices must lie in [0, {len(p)}), got [{grp.min()}, {grp.max()}]"
            )
        return p[grp].sum(axis=1)
    if grp.ndim == 1:
        if len(grp) != len(p):
            raise ValueError(f"groups: need one label per image ({len(p)}), got {len(grp)}")
        _, inv = np.unique(grp, return_inverse=True)
        out = np.zeros((inv.max() + 1 if inv.size else 0, p.shape[1]))
        np.add.at(out, inv, p)
        return out
    raise ValueError(f"groups must be None, (S, N) indices or (B,) labels, got shape {grp.shape}")


# ---------------------------------------------------------------------------------------
# MLE and test statistic
# ---------------------------------------------------------------------------------------
def refine_max(profile, gammas) -> tuple[np.ndarray, np.ndarray]:
    """Refined maximum ``(γ_MLE, ln r̂_max)`` of profiles ``(..., G)``, each ``(...)``.

    At the grid argmax ``k`` (first one on ties), fit the parabola through the nodes
    ``k−1, k, k+1`` (any spacing) and take its vertex, clipped to ``[γ_{k−1}, γ_{k+1}]``;
    the maximum value is the parabola at that point (never below the grid maximum).
    When ``k`` is the first (last) node, the parabola through the first (last) three
    nodes is used and its vertex clipped to the grid: a vertex beyond the prior range
    returns the edge node itself (the profile still rises towards the edge, the MLE is
    the edge), one within the first (last) cell is kept. When the three points are not
    strictly concave (flat top, linear profile) the grid node is kept.
    """
    g = check_grid(gammas)
    p = _check_profile(profile, g)
    k = np.argmax(p, axis=-1)
    kc = np.clip(k, 1, g.size - 2)
    y0 = np.take_along_axis(p, (kc - 1)[..., None], -1)[..., 0]
    y1 = np.take_along_axis(p, kc[..., None], -1)[..., 0]
    y2 = np.take_along_axis(p, (kc + 1)[..., None], -1)[..., 0]
    x0, x1, x2 = g[kc - 1], g[kc], g[kc + 1]
    # Parabola y = y1 + b (x − x1) + c (x − x1)²  through the three points (divided differences).
    d0, d2 = x0 - x1, x2 - x1
    s0, s2 = (y0 - y1) / d0, (y2 - y1) / d2
    c = (s2 - s0) / (d2 - d0)
    b = s0 - c * d0
    use = c < 0  # strictly concave through the three points
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = np.where(use, -b / (2 * np.where(use, c, -1.0)), 0.0)
    dx = np.clip(dx, d0, d2)
    g_hat = np.where(use, x1 + dx, g[k])
    v_hat = np.where(
        use, y1 + b * dx + c * dx * dx, np.take_along_axis(p, k[..., None], -1)[..., 0]
    )
    v_hat = np.maximum(v_hat, np.take_along_axis(p, k[..., None], -1)[..., 0])
    return g_hat, v_hat


def mle(profile, gammas):
    """γ_MLE of profiles ``(..., G)``: a float for one profile, an array ``(...)`` otherwise.

    Grid argmax refined by a 3-point parabola, clipped to the neighbouring nodes; at a
    grid edge the edge value (see :func:`refine_max`).
    """
    g_hat, _ = refine_max(profile, gammas)
    return float(g_hat) if np.ndim(g_hat) == 0 else g_hat


def test_statistic(profile, gammas) -> np.ndarray:
    """``t(γ_g) = 2 (ln r̂_max − ln r̂(γ_g))`` on the grid nodes, shape of ``profile``.

    ``ln r̂_max`` is the refined maximum of :func:`refine_max`, so ``t ≥ 0`` by
    construction; round-off negatives are clipped to 0.
    """
    g = check_grid(gammas)
    p = _check_profile(profile, g)
    _, v_hat = refine_max(p, g)
    return np.maximum(2.0 * (v_hat[..., None] - p), 0.0)


test_statistic.__test__ = False  # type: ignore[attr-defined]  # not a pytest test despite its name


def _augmented(t_row: np.ndarray, g: np.ndarray, g_hat: float) -> tuple[np.ndarray, np.ndarray]:
    """Nodes of the piecewise-linear ``t``: the grid plus ``(γ_MLE, 0)`` when off-node."""
    j = int(np.searchsorted(g, g_hat))
    if j < g.size and abs(g[j] - g_hat) <= 1e-12 * max(1.0, abs(g_hat)):
        t = t_row.copy()
        t[j] = 0.0
        return g, t
    return np.insert(g, j, g_hat), np.insert(t_row, j, 0.0)


def t_at(profile, gammas, gamma_true):
    """``t(γ_true)`` for profiles ``(..., G)`` and ``γ_true`` broadcastable to ``(...)``.

    ``t`` is linear between grid nodes, with ``(γ_MLE, 0)`` as an extra node, the same
    function whose sub-level set :func:`interval` returns, so ``t_at(γ) ≤ τ`` exactly
    when γ lies in the interval. ``γ_true`` outside the grid raises ``ValueError``.
    """
    g = check_grid(gammas)
    p = _check_profile(profile, g)
    g_hat, _ = refine_max(p, g)
    t = test_statistic(p, g)
    gt = np.broadcast_to(np.asarray(gamma_true, dtype=np.float64), g_hat.shape)
    if np.any(~np.isfinite(gt)) or np.any(gt < g[0]) or np.any(gt > g[-1]):
        raise ValueError(f"gamma_true must lie on the grid range [{g[0]}, {g[-1]}]")
    # Bracketing nodes [j−1, j] of γ_true.
    j = np.clip(np.searchsorted(g, gt, side="right"), 1, g.size - 1)
    xa, xb = g[j - 1], g[j]
    ta = np.take_along_axis(t, (j - 1)[..., None], -1)[..., 0]
    tb = np.take_along_axis(t, j[..., None], -1)[..., 0]
    # When γ_MLE lies strictly inside that bracket, the vertex (γ_MLE, 0) splits it.
    inside = (g_hat > xa) & (g_hat < xb)
    left = inside & (gt <= g_hat)
    right = inside & (gt > g_hat)
    xb = np.where(left, g_hat, xb)
    tb = np.where(left, 0.0, tb)
    xa = np.where(right, g_hat, xa)
    ta = np.where(right, 0.0, ta)
    w = (gt - xa) / (xb - xa)
    out = ta + w * (tb - ta)
    return float(out) if out.ndim == 0 else out


# ---------------------------------------------------------------------------------------
# intervals
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Interval:
    """The set ``{γ : t(γ) ≤ threshold}`` of one profile.

    ``lower``/``upper`` are the hull of all regions (what callers report, saying so when
    ``multimodal``); ``regions`` lists every ``(lo, hi)`` region in increasing order.
    ``lower_at_edge``/``upper_at_edge``: the hull reaches the first/last grid node, so the
    interval is open there (only a bound by the prior range, not a measurement).
    """

    mle: float
    lower: float
    upper: float
    threshold: float
    regions: tuple[tuple[float, float], ...]
    multimodal: bool
    lower_at_edge: bool
    upper_at_edge: bool

    @property
    def minus(self) -> float:
        """``γ_MLE − lower`` (≥ 0)."""
        return self.mle - self.lower

    @property
    def plus(self) -> float:
        """``upper − γ_MLE`` (≥ 0)."""
        return self.upper - self.mle

    def contains(self, gamma: float) -> bool:
        """Whether γ lies in one of the regions (not merely in the hull)."""
        return any(lo <= gamma <= hi for lo, hi in self.regions)

    def as_dict(self) -> dict:
        """Flat record for tables (``regions`` as a string)."""
        d = asdict(self)
        d["regions"] = ";".join(f"{lo:.6g}-{hi:.6g}" for lo, hi in self.regions)
        d["n_regions"] = len(self.regions)
        return d


def _crossing(xa, ta, xb, tb, tau):
    """γ where the line through ``(xa, ta)``, ``(xb, tb)`` reaches τ (ta, tb on both sides)."""
    return xa + (tau - ta) * (xb - xa) / (tb - ta)


def interval(profile, gammas, threshold: float) -> Interval:
    """68% (or any) interval ``{γ : t(γ) ≤ threshold}`` of one profile ``(G,)``.

    ``t`` is the piecewise-linear function of :func:`t_at` (grid nodes plus the vertex
    ``(γ_MLE, 0)``); region bounds are its exact crossings of the threshold, i.e. linear
    interpolation between the bracketing nodes. A region that reaches a grid end is
    closed at that node and flagged (``lower_at_edge``/``upper_at_edge`` refer to the
    hull). Several regions (a secondary minimum of ``t`` below the threshold) are all
    returned with ``multimodal=True``; ``lower``/``upper`` are then the hull.
    """
    g = check_grid(gammas)
    p = _check_profile(profile, g)
    if p.ndim != 1:
        raise ValueError(
            f"interval: one profile of shape (G,) at a time, got {p.shape}; use intervals()"
        )
    tau = float(threshold)
    if not (math.isfinite(tau) and tau > 0):
        raise ValueError(f"threshold must be finite and > 0, got {threshold!r}")
    g_hat, _ = refine_max(p, g)
    x, t = _augmented(test_statistic(p, g), g, float(g_hat))
    inside = t <= tau
    # Runs of consecutive inside nodes.
    edges = np.diff(np.concatenate(([0], inside.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    regions = []
    for i, j in zip(starts, stops, strict=True):
        lo = x[0] if i == 0 else _crossing(x[i - 1], t[i - 1], x[i], t[i], tau)
        hi = x[-1] if j == x.size - 1 else _crossing(x[j], t[j], x[j + 1], t[j + 1], tau)
        regions.append((float(lo), float(hi)))
    lower, upper = regions[0][0], regions[-1][1]
    return Interval(
        mle=float(g_hat),
        lower=lower,
        upper=upper,
        threshold=tau,
        regions=tuple(regions),
        multimodal=len(regions) > 1,
        lower_at_edge=bool(inside[0]),
        upper_at_edge=bool(inside[-1]),
    )


def intervals(profiles, gammas, threshold: float) -> list[Interval]:
    """:func:`interval` of every row of ``profiles (S, G)``."""
    p = np.asarray(profiles, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"intervals: profiles must have shape (S, G), got {p.shape}")
    return [interval(row, gammas, threshold) for row in p]


def intervals_frame(profiles, gammas, threshold: float, index: Sequence | None = None):
    """:func:`intervals` as a pandas DataFrame (one row per profile, :meth:`Interval.as_dict`)."""
    import pandas as pd

    rows = [iv.as_dict() for iv in intervals(profiles, gammas, threshold)]
    return pd.DataFrame(rows, index=None if index is None else list(index))


def profiles_to_t(
    profiles: Mapping[str, np.ndarray] | np.ndarray, gammas, *, kind: str = "log_ratio"
):
    """Convert ``ln r̂`` profiles to ``t`` (``kind='log_ratio'``) or pass ``t`` through (``'t'``)."""
    if kind not in ("log_ratio", "t"):
        raise ValueError(f"kind must be 'log_ratio' or 't', got {kind!r}")
    conv = (
        (lambda a: test_statistic(a, gammas))
        if kind == "log_ratio"
        else (lambda a: np.asarray(a, dtype=np.float64))
    )
    if isinstance(profiles, Mapping):
        return {k: conv(v) for k, v in profiles.items()}
    return conv(profiles)


__all__ += ["intervals_frame", "profiles_to_t"]
