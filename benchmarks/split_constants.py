"""Measure the error constants C_p(ρ) of the near/far population split (subslope.nearfar).

For one member at a random sub-grid position, the far field α·W (W the split weight
with r_c = ρ·h) is sampled at the nodes (every S-th grid point) and interpolated back
with the order-p Lagrange scheme of :func:`subslope.nearfar.interpolation_matrix`. The
ratio of the worst interpolation error over the grid (the image's 100 × 100 points,
the member anywhere on it, edges included) to the member's largest |α| on
the circle r = r_c (4 diagonal directions, as :func:`subslope.nearfar.member_rungs` computes it)
is recorded; C_p(ρ) is the worst ratio over the random members times ``--safety``.
Members: EPL with γ ~ U(1.01, 2.99), e ≤ 0.28 and any orientation; NFW and tNFW with
r_s / h ~ logU(0.1, 30) and τ ~ U(1, 30), when their pair kernels are available.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/split_constants.py [--members 60]

Prints a table and the ``ERROR_CONSTANTS`` literal for ``subslope/nearfar.py``.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from subslope import nearfar as NF
from subslope import pair_kernels as PK

F64 = torch.float64


def random_members(profile: str, n: int, h: float, m: int, rng: np.random.Generator,
                   where: str) -> list[dict[str, torch.Tensor]]:
    out = []
    for _ in range(n):
        if where == "interior":  # centre region: the member's zone and stencils stay inside
            off = rng.uniform(-0.5, 0.5, 2) * h
        else:  # anywhere on the grid, edges included
            off = rng.uniform(-0.5, 0.5, 2) * (m - 1) * 1.05
        if profile == "epl":
            e = rng.uniform(0, 0.28)
            phi = rng.uniform(0, np.pi)
            p = {"amp": 1.0, "gamma": rng.uniform(1.01, 2.99), "e1": e * np.cos(2 * phi), "e2": e * np.sin(2 * phi)}
        else:
            r_s = h * np.exp(rng.uniform(np.log(0.1), np.log(30)))
            p = {"r_s": r_s, "alpha_rs": 1.0}
            if profile == "tnfw":
                p["r_t"] = r_s * rng.uniform(1, 30)
        p["x"], p["y"] = off
        out.append({k: torch.tensor([[v]], dtype=F64) for k, v in p.items()})
    return out


def worst_ratio(profile: str, members, rho: float, order: int, spacing: int, m: int) -> float:
    h = float(spacing)  # grid step = 1
    ax1 = torch.arange(m, dtype=F64) - (m - 1) / 2
    yy, xx = torch.meshgrid(ax1, ax1, indexing="ij")
    x, y = xx.reshape(1, -1), yy.reshape(1, -1)
    nodes = NF.node_indices(m, spacing)
    L = NF.interpolation_matrix(m, nodes, order, F64, "cpu")
    nd = torch.as_tensor(nodes)
    worst = 0.0
    for p in members:
        table = PK.member_table(profile, p, 14)
        rc = rho * h
        fx, fy, _ = PK.far_sums(x, y, table, profile, torch.full((1, 1), 1.0 / rc**2, dtype=F64))
        err = 0.0
        for f in (fx, fy):
            g = f.reshape(m, m)
            gi = L @ g[nd][:, nd] @ L.T
            err = max(err, float((gi - g).abs().max()))
        rows = [table[:, k, :, None] for k in range(table.shape[1])]
        ang = torch.arange(4, dtype=F64) * (np.pi / 2) + np.pi / 4
        cax, cay, _ = PK.PAIR_FUNCTIONS[profile](rows[0] + rc * torch.cos(ang), rows[1] + rc * torch.sin(ang), rows)
        bound = float(torch.hypot(cax, cay).max())
        worst = max(worst, err / bound)
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
    profiles = [p for p in ("epl", "nfw", "tnfw") if p in PK.PAIR_FUNCTIONS]
    tables = {}
    for where in ("interior", "edge"):
        # interior: a grid large enough that no zone or stencil reaches an edge
        m = 2 * int(np.ceil((NF.RHO_LADDER[-1] + 5) * args.spacing)) + 1 if where == "interior" else args.grid
        pop = {p: random_members(p, args.members, float(args.spacing), m, rng, where) for p in profiles}
        consts = {}
        print(f"\n{where}: profiles {profiles}, {args.members} members each, spacing {args.spacing}, grid {m}²")
        print("| order | ρ | " + " | ".join(profiles) + " | C_p(ρ) |")
        print("|---|---|" + "---|" * len(profiles) + "---|")
        for order in (4, 6, 8):
            row = []
            for rho in NF.RHO_LADDER:
                w = {p: worst_ratio(p, pop[p], rho, order, args.spacing, m) for p in profiles}
                c = args.safety * max(w.values())
                row.append(c)
                print(f"| {order} | {rho:g} | " + " | ".join(f"{w[p]:.2e}" for p in profiles) + f" | {c:.2e} |",
                      flush=True)
            consts[order] = row
        tables[where] = consts
    for where, name in (("interior", "ERROR_CONSTANTS"), ("edge", "EDGE_ERROR_CONSTANTS")):
        print(f"{name} = {{")
        for order, row in tables[where].items():
            print(f"    {order}: (" + ", ".join(f"{v:.2g}" for v in row) + "),")
        print("}")


if __name__ == "__main__":
    main()
