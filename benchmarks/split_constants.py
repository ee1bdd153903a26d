"""Measure the error constants C_p(ρ) of the near/far population split (subslope.nearfar).

For one member at a random sub-grid position, the far field α·W (W the split weight
with r_c = ρ·h) is sampled at the nodes (every S-th grid point) and interpolated back
with the order-p Lagrange scheme of :func:`subslope.nearfar.interpolation_matrix`. The
ratio of the worst interpolation error over the grid (the image's 100 × 100 points,
the member anywhere on it, edges included) to the member's largest |α| on
the circle r = r_c (4 diagonal directions, as :func:`subslope.nearfar.member_rungs` computes it)
is recorded; C_p(ρ) is the worst ratio over the random members times ``--safety``.
Members, one class of constants each: EPL with γ uniform in each class of
:data:`subslope.nearfar.EPL_GAMMA_EDGES` (1.01 … 2.99), e ≤ 0.28 and any orientation;
NFW and tNFW with r_s / h ~ logU(0.1, 30) and τ ~ U(1, 30). The EPL constants depend
on γ (steep members, γ > 2.5, need up to 4× larger ones than γ ≈ 2), so members get
the constants of their own γ class.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/split_constants.py [--members 60]

Prints a table and the ``ERROR_CONSTANTS`` / ``EDGE_ERROR_CONSTANTS`` literals for
``subslope/nearfar.py``.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from subslope import nearfar as NF
from subslope import pair_kernels as PK

F64 = torch.float64


def random_members(profile: str, n: int, h: float, m: int, rng: np.random.Generator,
                   where: str, gamma: tuple[float, float] = (1.01, 2.99)) -> list[dict[str, torch.Tensor]]:
    out = []
    for _ in range(n):
        if where == "interior":  # centre region: the member's zone and stencils stay inside
            off = rng.uniform(-0.5, 0.5, 2) * h
        else:  # anywhere on the grid, edges included
            off = rng.uniform(-0.5, 0.5, 2) * (m - 1) * 1.05
        if profile == "epl":
            e = rng.uniform(0, 0.28)
            phi = rng.uniform(0, np.pi)
            p = {"amp": 1.0, "gamma": rng.uniform(*gamma), "e1": e * np.cos(2 * phi), "e2": e * np.sin(2 * phi)}
        else:
            r_s = h * np.exp(rng.uniform(np.log(0.1), np.log(30)))
            p = {"r_s": r_s, "alpha_rs": 1.0}
            if profile == "tnfw":
                p["r_t"] = r_s * rng.uniform(1, 30)
        p["x"], p["y"] = off
        out.append({k: torch.tensor([[v]], dtype=F64) for k, v in p.items()})
    return out


def worst_ratios(profile: str, members, rho: float, orders, spacing: int, m: int) -> dict[int, float]:
    """Worst ratio (interpolation error / max |α| on r = r_c) over ``members`` per order."""
    h = float(spacing)  # grid step = 1
    ax1 = torch.arange(m, dtype=F64) - (m - 1) / 2
    yy, xx = torch.meshgrid(ax1, ax1, indexing="ij")
    x, y = xx.reshape(1, -1), yy.reshape(1, -1)
    nodes = NF.node_indices(m, spacing)
    nd = torch.as_tensor(nodes)
    mats = {o: NF.interpolation_matrix(m, nodes, o, F64, "cpu") for o in orders}
    worst = dict.fromkeys(orders, 0.0)
    rc = rho * h
    for p in members:
        table = PK.member_table(profile, p, 14)
        fx, fy, _ = PK.far_sums(x, y, table, profile, torch.full((1, 1), 1.0 / rc**2, dtype=F64))
        rows = [table[:, k, :, None] for k in range(table.shape[1])]
        ang = torch.arange(4, dtype=F64) * (np.pi / 2) + np.pi / 4
        cax, cay, _ = PK.PAIR_FUNCTIONS[profile](rows[0] + rc * torch.cos(ang), rows[1] + rc * torch.sin(ang), rows)
        bound = float(torch.hypot(cax, cay).max())
        for o, L in mats.items():
            err = 0.0
            for f in (fx, fy):
                g = f.reshape(m, m)
                err = max(err, float((L @ g[nd][:, nd] @ L.T - g).abs().max()))
            worst[o] = max(worst[o], err / bound)
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--members", type=int, default=40)
    ap.add_argument("--spacing", type=int, default=3, help="node spacing in grid steps")
    ap.add_argument("--grid", type=int, default=100, help="grid points per side (the image)")
    ap.add_argument("--safety", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    edges = (1.01, *NF.EPL_GAMMA_EDGES, 2.99)
    classes = [("epl", (lo, hi)) for lo, hi in zip(edges[:-1], edges[1:])] + [("nfw", None), ("tnfw", None)]
    tables = {}
    for where in ("interior", "edge"):
        # interior: a grid large enough that no zone or stencil reaches an edge
        m = 2 * int(np.ceil((NF.RHO_LADDER[-1] + 5) * args.spacing)) + 1 if where == "interior" else args.grid
        print(f"\n{where}: {args.members} members per class, spacing {args.spacing}, grid {m}²")
        print("| class | order | " + " | ".join(f"ρ={r:g}" for r in NF.RHO_LADDER) + " |")
        print("|---|---|" + "---|" * len(NF.RHO_LADDER))
        consts: dict = {}
        for profile, gam in classes:
            members = random_members(profile, args.members, float(args.spacing), m, rng, where,
                                     **({"gamma": gam} if gam else {}))
            ratios = [worst_ratios(profile, members, rho, (4, 6, 8), args.spacing, m) for rho in NF.RHO_LADDER]
            for order in (4, 6, 8):
                row = [args.safety * r[order] for r in ratios]
                consts.setdefault(profile, {}).setdefault(order, []).append(row)
                label = f"{profile} γ∈[{gam[0]:g}, {gam[1]:g})" if gam else profile
                print(f"| {label} | {order} | " + " | ".join(f"{c:.2g}" for c in row) + " |", flush=True)
        tables[where] = consts
    for where, name in (("interior", "ERROR_CONSTANTS"), ("edge", "EDGE_ERROR_CONSTANTS")):
        print(f"{name} = {{")
        for profile, by_order in tables[where].items():
            print(f"    {profile!r}: {{")
            for order, rows in by_order.items():
                print(f"        {order}: (")
                for row in rows:
                    print("            (" + ", ".join(f"{v:.2g}" for v in row) + "),")
                print("        ),")
            print("    },")
        print("}")


if __name__ == "__main__":
    main()
