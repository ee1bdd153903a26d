"""Cost of one member–point pair of each subhalo profile's compiled kernel.

For EPL, NFW and tNFW members (``subslope.physics.pairs``), compiles
``direct_sums`` with and without the convergence and ``far_sums`` (the near/far split's
far-field kernel, which weights every pair by the partition of unity) and times them on
``--members`` random members at ``--points`` random points in a 5″ field, one thread.
Prints the median over ``--repeats`` calls in ns per pair: the unit of the split's cost
(docs/performance.md). Members are drawn over the subhalo ranges of the reduced scenes
(EPL: γ 1.1–2.9, |e| < 0.2; NFW/tNFW: r_s 0.05–0.35″, τ = r_t/r_s 2–12).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/pair_costs.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from subslope.physics.pairs.sums import direct_sums, far_sums, member_table
from subslope.render.settings import RenderSettings


def members(profile: str, n: int, g: torch.Generator) -> dict[str, torch.Tensor]:
    """``(1, n)`` parameters of random members of ``profile`` in a 5″ field."""

    def u(lo, hi):
        return lo + (hi - lo) * torch.rand(1, n, generator=g)

    centre = {"x": u(-2.5, 2.5), "y": u(-2.5, 2.5)}
    if profile == "epl":
        return {
            "amp": u(1e-4, 1e-2),
            "gamma": u(1.1, 2.9),
            "e1": u(-0.1, 0.1),
            "e2": u(-0.1, 0.1),
        } | centre
    r_s = u(0.05, 0.35)
    p = {"r_s": r_s, "alpha_rs": u(1e-4, 1e-3)} | centre
    if profile == "tnfw":
        p["r_t"] = r_s * u(2.0, 12.0)
    return p


def median_ns(fn, inputs: tuple, pairs: int, repeats: int) -> float:
    """Median wall time of ``fn(*inputs)`` per pair, ns (two warm-up calls compile it)."""
    fn(*inputs)
    fn(*inputs)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn(*inputs)
        times.append(time.perf_counter() - t)
    return float(np.median(times)) / pairs * 1e9


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--members", type=int, default=1500)
    ap.add_argument("--points", type=int, default=2601, help="51 x 51: the far-field nodes")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    g = torch.Generator().manual_seed(0)
    x, y = (5.0 * torch.rand(1, args.points, generator=g) - 2.5 for _ in range(2))
    inv_rc2 = torch.full((1, args.members), 1.0 / 0.1**2)
    pairs = args.members * args.points
    n_terms = RenderSettings().n_terms
    print(f"{args.members} members x {args.points} points, {torch.get_num_threads()} thread(s)")
    print("profile  direct+kappa  direct  far_sums   (ns per pair, median)")
    for profile in ("epl", "nfw", "tnfw"):
        table = member_table(profile, members(profile, args.members, g), n_terms)
        row = []
        for kappa in (True, False):
            f = torch.compile(
                lambda a, b, t, k=kappa, p=profile: direct_sums(a, b, t, p, k), dynamic=True
            )
            row.append(median_ns(f, (x, y, table), pairs, args.repeats))
        far = torch.compile(lambda a, b, t, w, p=profile: far_sums(a, b, t, p, w), dynamic=True)
        row.append(median_ns(far, (x, y, table, inv_rc2), pairs, args.repeats))
        print(f"{profile:7s}  {row[0]:12.2f}  {row[1]:6.2f}  {row[2]:8.2f}")


if __name__ == "__main__":
    main()
