"""Does the signal budget's linearised refit agree with a full refit of the smooth model?

For the first ``--images`` images (with subhalos) of a shard, the signal budget's own
per-image refit (:func:`subslope.stages.signal_budget.image_budget`: the noise-free
image with its subhalos fitted by the subhalo-free model, every smooth parameter free,
Gauss-Newton on the whitened residual inside the estimator's mask) with every
iteration run (no early stop); the Δχ² left is compared with the first, linearised step.

    OMP_NUM_THREADS=2 .venv/bin/python studies/refit_check.py \\
        results/simulate_shard/nfw/a4/shard_0.h5 --images 4
"""

from __future__ import annotations

import argparse
import json
import sys
import time


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
    from subslope.stages.signal_budget import image_budget

    rows = []
    with open_shard(args.shard) as shard:
        picked = [i for i in range(len(shard)) if int(shard.params["n_sub"][i]) > 0]
        for i in picked[: args.images]:
            t0 = time.perf_counter()
            inputs = stored_inputs(shard, [i], cosmos=args.cosmos)
            fixed, linear, full = image_budget(inputs, args.mask_factor, args.iterations, rtol=0.0)
            rows.append(
                {
                    "image": i,
                    "dchi2_fixed": fixed,
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
