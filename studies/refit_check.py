"""Does the signal budget's linearised refit agree with a full refit of the smooth model?

For the first ``--images`` images (with subhalos) of a shard, the noise-free image with
its subhalos is fitted by the subhalo-free model with every smooth parameter of the
signal budget free (:func:`subslope.stages.signal_budget.smooth_directions`), by
Gauss-Newton iterations on the whitened residual inside the estimator's mask (the
Jacobian by central differences at the current point, a step halved until χ² falls,
starting at the stored values); the Δχ² left is compared with the linearised refit of
:mod:`subslope.stages.signal_budget`.

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
    from subslope.stats.signal import delta_chi2, whiten

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
            def columns(u, names=names, residual=residual):
                out = []
                for k in range(len(names)):
                    e = np.zeros(len(names))
                    e[k] = 1.0
                    out.append((residual(u - e) - residual(u + e)) / 2.0)
                return np.stack(out, axis=1)

            u = np.zeros(len(names))
            r = residual(u)
            linear = None
            for _ in range(args.iterations):
                a = columns(u)
                step, *_ = np.linalg.lstsq(a, r, rcond=None)
                if linear is None:
                    linear = float(np.sum((r - a @ step) ** 2))
                for _halving in range(8):
                    trial = residual(u + step)
                    if np.sum(trial**2) < np.sum(r**2):
                        u, r = u + step, trial
                        break
                    step = step / 2.0
                else:
                    break
            full = float(np.sum(r**2))
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
