"""Does the signal budget's linearised refit agree with a full refit of the smooth model?

For the first ``--images`` images (with subhalos) of a shard, the noise-free image with
its subhalos is fitted by the subhalo-free model with every smooth parameter of the
signal budget free (:func:`subslope.stages.signal_budget.smooth_directions`), by
Gauss-Newton iterations on the whitened residual inside the estimator's mask
(:func:`subslope.stats.signal.gauss_newton_refit`, every iteration run: no early stop,
starting at the stored values); the Δχ² left is compared with the first, linearised step.

    OMP_NUM_THREADS=2 .venv/bin/python studies/refit_check.py \\
        results/simulate_shard/nfw/a4/shard_0.h5 --images 4
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("shard")
    ap.add_argument("--images", type=int, default=4)
    ap.add_argument("--mask-factor", type=float, default=1.5)
    ap.add_argument("--cosmos", nargs="+", default=None, help="COSMOS folders (default: stored)")
    ap.add_argument("--iterations", type=int, default=6)
    args = ap.parse_args(argv)

    from subslope.io.shards import open_shard
    from subslope.simulation.rerender import stored_inputs
    from subslope.stages.signal_budget import (
        budget_image,
        shifted,
        smooth_directions,
        step_of,
    )
    from subslope.stats.signal import delta_chi2, gauss_newton_refit, whiten

    rows = []
    with open_shard(args.shard) as shard:
        picked = [i for i in range(len(shard)) if int(shard.params["n_sub"][i]) > 0]
        for i in picked[: args.images]:
            t0 = time.perf_counter()
            b = budget_image(stored_inputs(shard, [i], cosmos=args.cosmos), args.mask_factor)
            names = smooth_directions(b.macro)
            steps = np.array([step_of(n) for n in names])
            target = (b.render(b.macro, None) + b.diff).numpy()  # the image with subhalos

            def model(u, names=names, steps=steps, b=b):
                return b.render(shifted(b.macro, names, u * steps), None).numpy()

            def residual(u, b=b, target=target):
                return whiten(target - model(u), b.sigma, b.w)[b.mask]

            # unknowns: offsets in units of each direction's step (1e-3 arcsec, ...); a
            # difference step of one unit keeps the float32 renders above their rounding
            linear, full, _ = gauss_newton_refit(
                residual, len(names), iterations=args.iterations, rtol=0.0
            )
            rows.append(
                {
                    "image": i,
                    "dchi2_fixed": delta_chi2(b.diff, b.sigma, b.mask, b.w),
                    "dchi2_linear_refit": linear,
                    "dchi2_full_refit": full,
                    "full_over_linear": full / linear if linear > 0 else float("nan"),
                    "seconds": round(time.perf_counter() - t0, 1),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
