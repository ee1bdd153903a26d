"""The CDM reading against the assumed subhalo abundance (rule measure_abundance,
:func:`subslope.stages.cdm_grid.measure_abundance`)."""

from __future__ import annotations

from matplotlib.figure import Figure

from subslope.figures.paper import C_NFW, C_TNFW
from subslope.figures.save import footer

__all__ = ["abundance_figure"]


def abundance_figure(
    table, *, expected: tuple[float, float, float] | None = None, run_name: str = "", source=None
) -> Figure:
    """Left: the median stack γ_MLE (and its 16–84% band) of the a = 1 sets against the
    largest subhalo count N_max of their prior U{0, N_max} (log axis), NFW and tNFW;
    right: the paired shift against the same sets without subhalos (± 1 SE).
    ``expected``: (low, mid, high) of the N_max whose mean count, N_max / 2, equals a CDM
    host's expected count (:mod:`subslope.physics.abundance`), shaded."""
    fig = Figure(figsize=(9.5, 4.2))
    ax_read, ax_shift = fig.subplots(1, 2, sharex=True)
    for profile, color, marker in (("nfw", C_NFW, "o"), ("tnfw", C_TNFW, "s")):
        sel = table[table["profile"] == profile].sort_values("n_sub_max")
        if not len(sel):
            continue
        n = sel["n_sub_max"].to_numpy(float)
        med, lo, hi = (sel[k].to_numpy(float) for k in ("median", "lo", "hi"))
        label = f"{profile.upper() if profile == 'nfw' else 'tNFW'} subhalos, a = 1"
        ax_read.errorbar(
            n,
            med,
            yerr=[med - lo, hi - med],
            fmt=marker + "-",
            color=color,
            ms=5,
            capsize=2.5,
            label=label,
        )
        shift, se = sel["shift_mean"].to_numpy(float), sel["shift_mean_se"].to_numpy(float)
        ax_shift.errorbar(n, shift, yerr=se, fmt=marker + "-", color=color, ms=5, capsize=2.5)
    ax_shift.axhline(0.0, color="0.4", lw=0.8)
    for ax in (ax_read, ax_shift):
        if expected is not None:
            ax.axvspan(expected[0], expected[2], color="0.85", lw=0, zorder=0)
            ax.axvline(
                expected[1],
                color="0.5",
                ls="--",
                lw=1,
                label="CDM host: 2 × expected count" if ax is ax_read else None,
            )
        ax.set_xscale("log")
        ax.set_xlabel(r"largest subhalo count $N_\mathrm{max}$ (prior U{0, $N_\mathrm{max}$})")
        ax.grid(alpha=0.25)
    ax_read.set_ylabel(r"stack $\gamma_\mathrm{MLE}$ (median, 16–84%)")
    ax_shift.set_ylabel(r"paired shift: with − without subhalos")
    ax_read.legend(fontsize=7, loc="best")
    footer(fig, run_name, source)
    fig.suptitle("The CDM reading against the assumed subhalo abundance", fontsize=10)
    fig.tight_layout(rect=(0, 0.04, 1, 0.95))
    return fig
