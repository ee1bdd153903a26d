"""Stage ``signal_budget``: how much signal the subhalos of each scene put into its images,
for an ideal observer (rules signal_budget, summarize_signal_budget; docs/inference.md).

For each of the first images of a shard, everything as stored: the noise-free image with
and without its subhalos (line-of-sight halos, lens, lens light, sky and source kept), the
per-pixel noise σ of the instrument (Poisson + sky + read noise of the subhalo-free
image; the drizzle correlation whitened, :mod:`subslope.stats.signal`), and inside the
estimator's mask (``training.mask_factor`` θ_E about the lens centre):

- ``dchi2_fixed``: Δχ² of the difference with the smooth model known;
- ``dchi2_linear``: what is left after a linearised refit of every smooth parameter the
  scene has (:data:`SMOOTH_KEYS`, the multipoles in Cartesian components), whose
  derivatives are central differences of the subhalo-free image;
- ``dchi2_refit``: what is left after the full (Gauss-Newton) refit of the same
  parameters (``signal_budget.refit_iterations``): at most ``dchi2_fixed``, and usually
  below the linearised value, though not always (the first step can fall short of what
  the linearisation predicts; the full refit then stops above it).

The source's morphology stays fixed, so all three are upper bounds on what an analysis that
also fits the source could see. An image without subhalos has Δχ² = 0 by definition.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from subslope.io.atomic import write_csv

__all__ = [
    "BUDGET_COLUMNS",
    "budget_image",
    "image_budget",
    "shifted",
    "smooth_directions",
    "step_of",
    "RESPONSE_COLUMNS",
    "response_table",
    "SMOOTH_KEYS",
    "budget_rows",
    "signal_budget_shard",
    "summarize_signal_budget",
    "CONTRAST_COLUMNS",
    "contrast_rows",
    "concentration_contrast",
]

log = logging.getLogger(__name__)

#: Smooth parameters refitted, each with its central-difference step (arcsec, radians,
#: magnitudes or e⁻/s, as the parameter); the multipoles are added as Cartesian pairs.
SMOOTH_KEYS = {
    "theta_e": 1e-3,
    "gamma_ml": 1e-3,
    "lens_e1": 1e-3,
    "lens_e2": 1e-3,
    "lens_x": 1e-3,
    "lens_y": 1e-3,
    "shear_g1": 1e-3,
    "shear_g2": 1e-3,
    "light_e1": 1e-3,
    "light_e2": 1e-3,
    "light_mag": 1e-3,
    "light_n": 1e-3,
    "light_r": 1e-3,
    "sky_level": 1e-3,
    "src_x": 1e-3,
    "src_y": 1e-3,
    "src_rotation": 1e-3,
}
#: Multipole orders and the (amplitude, angle) keys of each; step of each component.
MULTIPOLES = ((3, "a3", "phi3"), (4, "a4", "phi4"))
MULTIPOLE_STEP = 1e-4

BUDGET_COLUMNS = (
    "scene",
    "multiplier",
    "image",
    "set_index",
    "n_sub",
    "gamma",
    "dchi2_fixed",
    "dchi2_linear",
    "dchi2_refit",
)


def smooth_directions(macro: dict[str, np.ndarray]) -> list[str]:
    """The smooth parameters of a one-image ``macro`` that the refit moves: the keys of
    :data:`SMOOTH_KEYS` it has, then ``a3_c``, ``a3_s``, ``a4_c``, ``a4_s`` (the
    multipoles' Cartesian components) where it has multipoles."""
    names = [key for key in SMOOTH_KEYS if key in macro]
    for _, amp, ang in MULTIPOLES:
        if amp in macro and ang in macro:
            names += [f"{amp}_c", f"{amp}_s"]
    return names


def step_of(name: str) -> float:
    """The central-difference step of a direction of :func:`smooth_directions`."""
    return SMOOTH_KEYS.get(name, MULTIPOLE_STEP)


def shifted(macro: dict[str, np.ndarray], names, offsets) -> dict[str, np.ndarray]:
    """``macro`` moved by ``offsets`` along the directions ``names``
    (:func:`smooth_directions`): added to a parameter, or to a multipole's Cartesian
    component ``a·cos mφ`` (``_c``) or ``a·sin mφ`` (``_s``)."""
    out = dict(macro)
    off = dict(zip(names, offsets))
    for m, amp, ang in MULTIPOLES:
        dx, dy = off.get(f"{amp}_c", 0.0), off.get(f"{amp}_s", 0.0)
        if amp in macro and ang in macro and (dx or dy):  # untouched: exactly as stored
            cx = macro[amp] * np.cos(m * macro[ang]) + dx
            cy = macro[amp] * np.sin(m * macro[ang]) + dy
            out[amp], out[ang] = np.hypot(cx, cy), np.arctan2(cy, cx) / m
    for name, value in zip(names, offsets):
        if name in SMOOTH_KEYS:
            out[name] = macro[name] + value
    return out


def _noise_weight(instrument) -> float:
    """Kernel side weight ``w`` of the instrument's noise correlation (a range: its
    midpoint, the images' per-image values being drawn from it)."""
    from subslope.physics.instrument import noise_kernel_weight

    rho = instrument.noise_correlation
    rho = 0.5 * (rho[0] + rho[1]) if isinstance(rho, tuple) else float(rho)
    return noise_kernel_weight(rho)


@dataclass
class BudgetImage:
    """One image of the signal budget: ``render(macro, subhalos)`` (noise-free, float64,
    everything else as stored), its ``macro``, the difference ``diff`` that its subhalos
    make, the noise ``sigma``, the estimator's ``mask`` and the correlation weight ``w``."""

    render: Any
    macro: dict
    subhalos: Any
    diff: np.ndarray
    sigma: np.ndarray
    mask: np.ndarray
    w: float


def budget_image(inp: dict[str, Any], mask_factor: float, baseline_subhalos=None) -> BudgetImage:
    """The :class:`BudgetImage` of the one image of the stored inputs ``inp``
    (:func:`subslope.simulation.rerender.stored_inputs`). ``baseline_subhalos``: the
    population whose image stands in for the subhalo-free one (``diff`` = image with
    ``inp``'s subhalos − image with these; the σ map is still the subhalo-free image's)."""
    import torch

    from subslope.physics.grid import pixel_grid
    from subslope.physics.instrument import noise_sigma_map
    from subslope.render.pipeline import render

    def image(macro, subhalos):
        out = render(
            macro,
            inp["psf"],
            inp["settings"],
            sources=inp["sources"],
            subhalos=subhalos,
            los=inp["los"],
            sheet_centre=inp["sheet_centre"],
        )[0]
        return out.detach().cpu().to(torch.float64)

    macro = inp["macro"]
    without = image(macro, None)
    base = without if baseline_subhalos is None else image(macro, baseline_subhalos)
    diff = (image(macro, inp["subhalos"]) - base).numpy()
    sigma = noise_sigma_map(without, inp["instrument"]).numpy()
    x, y = pixel_grid(diff.shape[-1], inp["instrument"].pixel_scale, dtype=torch.float64)
    r2 = (x.numpy() - macro["lens_x"][0]) ** 2 + (y.numpy() - macro["lens_y"][0]) ** 2
    mask = r2 <= (mask_factor * macro["theta_e"][0]) ** 2
    return BudgetImage(
        image, macro, inp["subhalos"], diff, sigma, mask, _noise_weight(inp["instrument"])
    )


def image_budget(
    inp: dict[str, Any],
    mask_factor: float,
    iterations: int,
    baseline_subhalos=None,
    *,
    rtol: float = 1e-3,
) -> tuple[float, float, float]:
    """``(dchi2_fixed, dchi2_linear, dchi2_refit)`` of the one image of the stored inputs
    ``inp``: the image with its subhalos fitted by the subhalo-free model, every smooth
    direction free (offsets in units of :func:`step_of`, so a unit difference step keeps
    a float32 render above its rounding), by :func:`subslope.stats.signal.gauss_newton_refit`
    of at most ``iterations`` iterations (``rtol``: its early stop; 0 runs them all).
    With ``baseline_subhalos`` the model is the image with those subhalos instead, their
    perturbation held fixed while the smooth parameters move (to first order in the
    small refit steps)."""
    from subslope.stats.signal import delta_chi2, gauss_newton_refit, whiten

    b = budget_image(inp, mask_factor, baseline_subhalos)
    names = smooth_directions(b.macro)
    steps = np.array([step_of(n) for n in names])
    target = b.render(b.macro, None).numpy() + b.diff

    def residual(u):
        model = b.render(shifted(b.macro, names, u * steps), None).numpy()
        return whiten(target - model, b.sigma, b.w)[b.mask]

    fixed = delta_chi2(b.diff, b.sigma, b.mask, b.w)
    linear, full, _ = gauss_newton_refit(residual, len(names), iterations=iterations, rtol=rtol)
    return fixed, linear, full


def budget_rows(
    shard_path,
    n_images: int,
    *,
    mask_factor: float,
    scene: str,
    multiplier=None,
    cosmos=None,
    iterations: int = 6,
) -> list[dict[str, Any]]:
    """One row (:data:`BUDGET_COLUMNS`) per image of the first ``n_images`` of a shard;
    ``cosmos``: this campaign's COSMOS folders (a shard from the cache may name another
    campaign's); ``iterations``: of the full refit (1: the linearised refit alone)."""
    from subslope.io.shards import open_shard
    from subslope.simulation.rerender import stored_inputs

    rows = []
    with open_shard(shard_path) as shard:
        n = min(int(n_images), len(shard))
        has_subhalos = shard.attrs["subhalo_profile"] != "none"
        for i in range(n):
            macro = {k: np.asarray(v[i : i + 1]) for k, v in shard.params.items()}
            if has_subhalos and int(macro["n_sub"][0]) > 0:
                inputs = stored_inputs(shard, [i], cosmos=cosmos)
                fixed, linear, refit = image_budget(inputs, mask_factor, iterations)
            else:
                fixed = linear = refit = 0.0
            rows.append(
                {
                    "scene": scene,
                    "multiplier": "" if multiplier is None else float(multiplier),
                    "image": i,
                    "set_index": int(macro["set_index"][0]) if "set_index" in macro else i,
                    "n_sub": int(macro["n_sub"][0]) if "n_sub" in macro else 0,
                    "gamma": float(macro["gamma_sub"][0]) if "gamma_sub" in macro else math.nan,
                    "dchi2_fixed": fixed,
                    "dchi2_linear": linear,
                    "dchi2_refit": refit,
                }
            )
    return rows


#: Columns of ``concentration_contrast.csv``: per image of a CDM scene, the Δχ² between
#: its image at ``a_high`` and at ``a_low`` (the same draw, only the concentrations
#: differ), smooth model fixed, linearised and fully refitted.
CONTRAST_COLUMNS = (
    "scene",
    "a_low",
    "a_high",
    "image",
    "set_index",
    "n_sub",
    "dchi2_fixed",
    "dchi2_linear",
    "dchi2_refit",
)


def contrast_rows(
    shard_low,
    shard_high,
    n_images: int,
    *,
    mask_factor: float,
    scene: str,
    multipliers: tuple[float, float],
    cosmos=None,
    iterations: int = 6,
) -> list[dict[str, Any]]:
    """How much the images can say about the concentration, from above: for each of the
    first ``n_images`` images of two shards of one CDM scene at multipliers ``a_low`` and
    ``a_high`` (the same lenses, sources, subhalo masses and positions, LoS halos and
    noise: common draws), the Δχ² of the ``a_high`` image against the ``a_low`` one, the
    smooth model refitted with the ``a_low`` subhalos' perturbation in place (the signal
    budget with the ``a_low`` image standing in for the subhalo-free one). An ideal
    observer that knows every subhalo's position and mass; the bound for one that must
    also infer them is lower."""
    from subslope.io.shards import open_shard
    from subslope.simulation.rerender import stored_inputs

    rows = []
    with open_shard(shard_low) as lo, open_shard(shard_high) as hi:
        n = min(int(n_images), len(lo), len(hi))
        for key in ("set_index", "theta_e", "n_sub"):
            if not np.array_equal(lo.params[key][:n], hi.params[key][:n]):
                raise ValueError(
                    f"{shard_low} and {shard_high} do not hold the same draws ({key} differs): "
                    "the contrast needs common draws"
                )
        for i in range(n):
            macro = {k: np.asarray(v[i : i + 1]) for k, v in lo.params.items()}
            if int(macro["n_sub"][0]) > 0:
                low = stored_inputs(lo, [i], cosmos=cosmos)
                high = stored_inputs(hi, [i], cosmos=cosmos)
                fixed, linear, refit = image_budget(
                    high, mask_factor, iterations, baseline_subhalos=low["subhalos"]
                )
            else:
                fixed = linear = refit = 0.0
            rows.append(
                {
                    "scene": scene,
                    "a_low": float(multipliers[0]),
                    "a_high": float(multipliers[1]),
                    "image": i,
                    "set_index": int(macro["set_index"][0]),
                    "n_sub": int(macro["n_sub"][0]),
                    "dchi2_fixed": fixed,
                    "dchi2_linear": linear,
                    "dchi2_refit": refit,
                }
            )
    return rows


def concentration_contrast(groups: Sequence, out_csv, n_images: int, **options: Any) -> Path:
    """Rule concentration_contrast: :func:`contrast_rows` of every ``(scene, a_low,
    a_high, shard at a_low, shard at a_high)`` of ``groups``, one row per image."""
    rows = []
    for scene, a_low, a_high, low, high in groups:
        got = contrast_rows(
            low, high, n_images, scene=scene, multipliers=(a_low, a_high), **options
        )
        log.info(
            "%s a = %g vs %g: median dchi2 fixed %.3g, refit %.3g over %d images",
            scene,
            a_low,
            a_high,
            float(np.median([r["dchi2_fixed"] for r in got])) if got else math.nan,
            float(np.median([r["dchi2_refit"] for r in got])) if got else math.nan,
            len(got),
        )
        rows += got
    return write_csv(out_csv, rows, list(CONTRAST_COLUMNS))


def signal_budget_shard(shard_path, out_csv, n_images: int, **options: Any) -> Path:
    """Rule signal_budget: :func:`budget_rows` of one shard (``options``: its keywords)
    written to ``out_csv``."""
    rows = budget_rows(shard_path, n_images, **options)
    scene = options.get("scene", "")
    log.info(
        "%s: median dchi2 fixed %.3g, refit %.3g over %d images",
        scene,
        float(np.median([r["dchi2_fixed"] for r in rows])) if rows else math.nan,
        float(np.median([r["dchi2_refit"] for r in rows])) if rows else math.nan,
        len(rows),
    )
    return write_csv(out_csv, rows, list(BUDGET_COLUMNS))


SUMMARY_COLUMNS = (
    "scene",
    "multiplier",
    "n_images",
    "fixed_p16",
    "fixed_p50",
    "fixed_p84",
    "refit_p16",
    "refit_p50",
    "refit_p84",
    "linear_p50",
    "stack_fixed",
    "stack_refit",
)


def summarize_signal_budget(
    csv_paths: Sequence, out_csv, fig_stem, *, stack_size: int, run_name: str
):
    """The table of the signal budget, one row per scene (and multiplier): the 16/50/84%
    of Δχ² per image with the smooth model fixed and refitted in full, the median after
    the linearised refit (``linear_p50``), and ``stack_fixed`` /
    ``stack_refit``, the Δχ² of a stack of ``stack_size`` images (``stack_size`` × the
    median, Δχ² adding over independent images); and its figure. Returns the table (pandas)."""
    import pandas as pd

    frames = [pd.read_csv(p) for p in csv_paths]
    data = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=BUDGET_COLUMNS)
    rows, labels, fixed_sets, refit_sets = [], [], [], []
    for (scene, mult), group in data.groupby(["scene", data["multiplier"].fillna(-1)], sort=False):
        fixed, refit = group["dchi2_fixed"].to_numpy(), group["dchi2_refit"].to_numpy()
        q = np.percentile
        rows.append(
            {
                "scene": scene,
                "multiplier": "" if mult == -1 else float(mult),
                "n_images": len(group),
                "fixed_p16": float(q(fixed, 16)),
                "fixed_p50": float(q(fixed, 50)),
                "fixed_p84": float(q(fixed, 84)),
                "refit_p16": float(q(refit, 16)),
                "refit_p50": float(q(refit, 50)),
                "refit_p84": float(q(refit, 84)),
                "linear_p50": float(np.median(group["dchi2_linear"]))
                if "dchi2_linear" in group
                else math.nan,
                "stack_fixed": float(stack_size * np.median(fixed)),
                "stack_refit": float(stack_size * np.median(refit)),
            }
        )
        labels.append(scene if mult == -1 else f"{scene} a={float(mult):g}")
        fixed_sets.append(fixed)
        refit_sets.append(refit)
    table = pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
    write_csv(out_csv, table.to_dict("records"), list(SUMMARY_COLUMNS))
    from subslope.figures.save import save_figure
    from subslope.figures.signal import signal_budget_figure

    fig = signal_budget_figure(
        labels,
        fixed_sets,
        refit_sets,
        run_name=run_name,
        source="results/signal_budget/signal_budget.csv",
    )
    save_figure(fig, fig_stem, run_name=run_name)
    return table


RESPONSE_COLUMNS = (
    "scene",
    "multiplier",
    "stack_refit",
    "stack_fixed",
    "shift",
    "shift_se",
    "paired",
    "visible",
)


def response_table(signal_csv, visibility_csv=None, halo_free_csv=None):
    """The estimator's response against the ideal observer's signal, one row per scene:
    ``stack_refit`` / ``stack_fixed``, the Δχ² of a stack (stack size × the median per
    image, refitted and fixed), and ``shift``, how far removing the halos moves the stack
    γ_MLE. CDM scenes (every multiplier): the mean paired shift against the same sets
    without their subhalos and its standard error (``cdm_visibility.csv``). EPL test sets:
    the median stack γ_MLE of the originals minus that of the same sets without subhalos
    and line-of-sight halos (``halo_free.csv``, sheets removed; not paired, no error).
    The Δχ² bounds the detection of subhalos of known positions and masses; it says
    nothing by itself about what the images can tell of their concentration
    (:func:`contrast_rows` bounds that)."""
    import pandas as pd

    signal = pd.read_csv(signal_csv)
    rows = []
    if visibility_csv:
        vis = pd.read_csv(visibility_csv)
        for r in vis.itertuples():
            match = signal[(signal["scene"] == r.scene) & (signal["multiplier"] == r.multiplier)]
            if len(match):
                s = match.iloc[0]
                rows.append(
                    {
                        "scene": r.scene,
                        "multiplier": float(r.multiplier),
                        "stack_refit": float(s["stack_refit"]),
                        "stack_fixed": float(s["stack_fixed"]),
                        "shift": float(r.shift_mean),
                        "shift_se": float(r.shift_mean_se),
                        "paired": True,
                        "visible": str(r.visible).lower() == "true",
                    }
                )
    if halo_free_csv:
        hf = pd.read_csv(halo_free_csv).set_index("variant")
        epl = signal[signal["scene"] == "test_epl"]
        if {"original", "sheets_removed"} <= set(hf.index) and len(epl):
            s = epl.iloc[0]
            rows.append(
                {
                    "scene": "test_epl",
                    "multiplier": math.nan,
                    "stack_refit": float(s["stack_refit"]),
                    "stack_fixed": float(s["stack_fixed"]),
                    "shift": float(
                        hf.loc["original", "stack_mle_p50"]
                        - hf.loc["sheets_removed", "stack_mle_p50"]
                    ),
                    "shift_se": math.nan,
                    "paired": False,
                    "visible": math.nan,
                }
            )
    return pd.DataFrame(rows, columns=list(RESPONSE_COLUMNS))
