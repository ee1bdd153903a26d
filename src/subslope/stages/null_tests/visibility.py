"""Stage ``null_tests``, visibility part: do the subhalos of the CDM sets reach the
estimator? (rules
subhalo_free_profiles, cdm_visibility; docs/inference.md).

The stack γ_MLE of a CDM set (figure 4, the a = 1 prediction) mixes two things: what
the estimator reads from the set's subhalos and what it reads from an image without
visible perturbations, which under the training prior is not flat (an image that shows
nothing is likelier at low γ). The second part alone is measured by re-rendering every
image of the set from its stored parameters without its subhalos — the same lens,
source, lens light, sky, line-of-sight halos and noise seeds
(:func:`subslope.simulation.rerender.subhalo_free_images`) — and pushing the re-renders
through the same inference. Per set, the shift

.. math:: \\Delta_s = \\hat\\gamma_{\\rm MLE}(\\text{set } s) -
          \\hat\\gamma_{\\rm MLE}(\\text{set } s \\text{ without subhalos})

is what the subhalos add. The table gives, per scene, the median stack γ_MLE with and
without the subhalos, the mean shift with its standard error, the fraction of sets whose
γ_MLE moved, and the two-sided Wilcoxon signed-rank p-value of the shifts against 0.
Subhalos that do not reach the estimator (p ≥ ``alpha``) leave a CDM band that is the
estimator's reading of subhalo-free images: it cannot order NFW against tNFW.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from subslope.io.atomic import write_text
from subslope.io.ratio_profiles import read_profiles
from subslope.stages.calibrate import set_stacks

__all__ = ["VISIBILITY_COLUMNS", "paired_stack_mles", "visibility_row", "cdm_visibility"]

log = logging.getLogger(__name__)

#: Columns of ``cdm_visibility.csv``, one row per CDM scene.
VISIBILITY_COLUMNS = (
    "scene",
    "multiplier",
    "n_sets",
    "stack_mle_p50",
    "subhalo_free_mle_p50",
    "shift_mean",
    "shift_mean_se",
    "shift_p50",
    "moved",
    "wilcoxon_p",
    "visible",
)


def paired_stack_mles(original: Sequence, removed: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """Stack γ_MLE of every set in the profiles files ``original`` and in their re-renders
    ``removed`` (same shards, same order), paired by set. Refuses files whose images do not
    pair (a different count, set or mask geometry)."""
    a, b = read_profiles(list(original)), read_profiles(list(removed))
    for key in ("set_id", "theta_e", "lens_x", "lens_y"):
        if a[key].shape != b[key].shape or not np.array_equal(a[key], b[key]):
            raise ValueError(
                f"visibility: the re-rendered profiles {list(removed)} do not pair with "
                f"{list(original)} image by image ({key} differs)"
            )
    return set_stacks(a)["mle"], set_stacks(b)["mle"]


def visibility_row(
    scene: str, with_subhalos, without, alpha: float = 0.05, multiplier: float = 1.0
) -> dict[str, Any]:
    """The :data:`VISIBILITY_COLUMNS` row of one scene and concentration multiplier from
    the paired stack γ_MLE of its sets with and without their subhalos. ``visible``: the
    Wilcoxon signed-rank test rejects a zero shift at level ``alpha`` (a scene whose sets
    never move is not visible, p = 1)."""
    from scipy.stats import wilcoxon

    x = np.asarray(with_subhalos, dtype=np.float64)
    y = np.asarray(without, dtype=np.float64)
    shift = x - y
    n = int(shift.size)
    p = float(wilcoxon(x, y).pvalue) if np.any(shift != 0) else 1.0
    return {
        "scene": scene,
        "multiplier": float(multiplier),
        "n_sets": n,
        "stack_mle_p50": float(np.median(x)) if n else math.nan,
        "subhalo_free_mle_p50": float(np.median(y)) if n else math.nan,
        "shift_mean": float(shift.mean()) if n else math.nan,
        "shift_mean_se": float(shift.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan,
        "shift_p50": float(np.median(shift)) if n else math.nan,
        "moved": float(np.mean(shift != 0)) if n else math.nan,
        "wilcoxon_p": p,
        "visible": bool(p < alpha),
    }


def cdm_visibility(files: Mapping[str, tuple[Sequence, Sequence]], out_csv, *, alpha: float = 0.05):
    """Table ``cdm_visibility.csv`` (:data:`VISIBILITY_COLUMNS`): ``files[key]`` is the
    pair (profiles files of the shards of one scene and multiplier, profiles files of
    their subhalo-free re-renders), ``key`` a ``(scene, multiplier)`` pair or a scene
    name (multiplier 1). Returns the table."""
    import pandas as pd

    rows = []
    for key, (original, removed) in files.items():
        scene, mult = key if isinstance(key, tuple) else (key, 1.0)
        paired = paired_stack_mles(original, removed)
        row = visibility_row(scene, *paired, alpha=alpha, multiplier=float(mult))
        log.info("visibility %s: %s", scene, row)
        rows.append(row)
    table = pd.DataFrame(rows, columns=VISIBILITY_COLUMNS)
    write_text(out_csv, table.to_csv(index=False))
    return table
