"""docs/simulation.md stiff cases: N_sub = 1500 EPL subhalos on the arc at γ = 2.5 and γ = 1.2.

Renders one train-scene system (seed 6: Sérsic source; seed 3 also printed; lens light,
LoS and noise off; empirical F814W PSF; float64) with
:func:`subslope.validation.stiff.stiff_cases`, with and without the negative sheet, prints the
table of docs/simulation.md ("Stiff cases"), cross-checks every image against
lenstronomy on identical inputs (skipped if lenstronomy is missing) and writes
results/figures/stiff_cases.png (seed 6).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/stiff_cases.py
"""

from __future__ import annotations

import time

import numpy as np
import torch

from subslope.figures.gallery import stiff_cases_figure
from subslope.render import pipeline as R
from subslope.validation import stiff as D
from subslope.validation.lenstronomy import lenstronomy_model

try:
    from render_speed import psf_kernel  # run as a script from benchmarks/ or the repo root
except ImportError:  # pragma: no cover
    from benchmarks.render_speed import psf_kernel

SEEDS = (6, 3)
FIGURE = "results/figures/stiff_cases.png"


def main() -> None:
    torch.set_num_threads(1)
    psf = psf_kernel()
    settings = R.RenderSettings(
        device="cpu", dtype=torch.float64, compile="off", n_terms=30, n_terms_main=30
    )
    for seed in SEEDS:
        t = time.perf_counter()
        res = D.stiff_cases(psf, seed=seed, settings=settings, centres=("origin", "mass_centroid"))
        print(f"\nseed {seed} ({time.perf_counter() - t:.0f} s)")
        print(D.format_table(res["cases"]))
        try:
            import lenstronomy  # noqa: F401
        except ImportError:
            print("lenstronomy not installed: cross-check skipped")
        else:
            for c in res["cases"][1:]:
                m = dict(res["macro"], gamma_sub=np.array([c.gamma]))
                ref = lenstronomy_model(
                    m,
                    psf.numpy(),
                    0,
                    subhalos=res["subhalos"][c.gamma],
                    sheets=c.sheet,
                    epl="EPL",
                    sheet_centre=c.sheet_centre,
                ).image()
                ours = res["images"][c.label]
                print(
                    f"  {c.label}: relative L2 vs lenstronomy "
                    f"{np.linalg.norm(ours - ref) / np.linalg.norm(ref):.1e}"
                )
        if seed == SEEDS[0]:
            stiff_cases_figure(res, [FIGURE], run_name=f"benchmarks/stiff_cases.py seed {seed}")
            print(f"wrote {FIGURE}")


if __name__ == "__main__":
    main()
