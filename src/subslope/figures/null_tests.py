"""The null-test figure: mean profiles and γ_MLE of scenes in which γ cannot be seen
(:mod:`subslope.stages.null_tests`)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from matplotlib import colormaps
from matplotlib.figure import Figure

from subslope.figures.save import footer

__all__ = ["null_test_figure"]


def null_test_figure(
    gammas,
    mean_profiles: Mapping[str, np.ndarray],
    mles: Mapping[str, Mapping[str, np.ndarray]],
    table,
    *,
    run_name: str,
    source: str | None = None,
) -> Figure:
    """Left: the mean single-image ln r̂(γ) of every null scene, less its maximum (flat
    for an estimator that reads γ from the subhalos only). Right: the γ_MLE of the single
    images (thin) and of the stacks (thick) of every scene, as histograms over the prior
    (spread out for such an estimator); the legend gives the fraction of stack intervals
    that exclude part of the prior."""
    g = np.asarray(gammas, dtype=np.float64)
    fig = Figure(figsize=(9.0, 4.0))
    ax1, ax2 = fig.subplots(1, 2)
    cmap = colormaps["tab10"]
    edges = np.linspace(g[0], g[-1], 19)
    by_scene = table.set_index("scene")
    for i, (scene, mean) in enumerate(mean_profiles.items()):
        color = cmap(i % 10)
        row = by_scene.loc[scene]
        ax1.plot(g, mean, color=color, lw=1.8, label=f"{scene} ({int(row['n_images'])} images)")
        ax2.hist(
            mles[scene]["single"], bins=edges, density=True, histtype="step", color=color, lw=0.8
        )
        ax2.hist(
            mles[scene]["stack"], bins=edges, density=True, histtype="step", color=color, lw=2,
            label=(
                f"{scene}: {row['stack_excluding']:.0%} of {int(row['n_stacks'])} stacks of "
                f"{int(row['n_per_stack'])} exclude part of the prior"
            ),
        )  # fmt: skip
    ax1.axhline(0, color="0.5", lw=0.8, ls="--")
    ax1.set_xlabel(r"$\gamma$")
    ax1.set_ylabel(r"mean $\ln\hat r(\gamma)$ $-$ its maximum")
    ax1.set_title("mean single-image profile (flat: nothing read)", fontsize=8)
    ax1.grid(alpha=0.25)
    ax1.legend(fontsize=7, frameon=False)
    ax2.axhline(1 / (g[-1] - g[0]), color="0.5", lw=0.8, ls="--", label="uniform over the prior")
    ax2.set_xlabel(r"$\gamma_\mathrm{MLE}$ (thin: single images, thick: stacks)")
    ax2.set_ylabel("density")
    ax2.grid(alpha=0.25)
    ax2.legend(fontsize=6.5, frameon=False, loc="upper left")
    footer(fig, run_name, source)
    fig.suptitle("Null tests: scenes in which the subhalo slope cannot be seen", fontsize=10)
    fig.tight_layout(rect=(0, 0.035, 1, 0.95))
    return fig
