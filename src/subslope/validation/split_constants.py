"""Measurement of the error constants ``C_p(ρ)`` of the near/far population split.

For one member at a random sub-grid position, the far field ``α·W`` (``W`` the split
weight with ``r_c = ρ·h``) is sampled at the nodes (every ``S``-th grid point) and
interpolated back with the order-``p`` Lagrange scheme of
:func:`subslope.render.nearfar.interpolation_matrix`. The ratio of the worst
interpolation error over the grid to the member's largest ``|α|`` on the circle
``r = r_c`` (4 diagonal directions, as :func:`subslope.render.nearfar.member_rungs`
computes it) is recorded; ``C_p(ρ)`` is the worst ratio over the random members of a
class times a safety factor.

Classes (one row of constants each): EPL members with γ uniform in each class of
``EPL_GAMMA_EDGES`` (1.01 … 2.99), ellipticity ≤ 0.28, any orientation; NFW and tNFW
members with ``r_s / h ~ logU(0.1, 30)`` and ``τ ~ U(1, 30)``. Two placements: the
``interior`` (a grid large enough that no zone or stencil reaches an edge) and the
``edge`` case (anywhere on the ``grid × grid`` image, edges included).

``benchmarks/split_constants.py`` runs this for every class and writes the data file
``subslope/render/split_constants.json`` that the renderer reads.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import torch

from subslope.physics.pairs import sums as pair_sums
from subslope.render import nearfar

__all__ = [
    "ORDERS",
    "PLACEMENTS",
    "constant_classes",
    "grid_side",
    "random_members",
    "worst_ratios",
    "class_rows",
    "measure_tables",
    "round_significant",
]

F64 = torch.float64
ORDERS = (4, 6, 8)
PLACEMENTS = ("interior", "edge")


def constant_classes(gamma_edges: Sequence[float]) -> list[tuple[str, tuple[float, float] | None]]:
    """``(profile, γ range or None)`` of every class, in the order of the tables' rows."""
    edges = (1.01, *gamma_edges, 2.99)
    return [("epl", (lo, hi)) for lo, hi in zip(edges[:-1], edges[1:])] + [
        ("nfw", None),
        ("tnfw", None),
    ]


def grid_side(where: str, spacing: int, grid: int, rho_ladder: Sequence[float]) -> int:
    """Grid points per side: ``grid`` for ``edge``; for ``interior`` a grid on which the
    largest zone of the ladder and its stencils never reach an edge."""
    if where == "edge":
        return int(grid)
    return 2 * int(np.ceil((rho_ladder[-1] + 5) * spacing)) + 1


def random_members(
    profile: str,
    n: int,
    h: float,
    m: int,
    rng: np.random.Generator,
    where: str,
    gamma: tuple[float, float] = (1.01, 2.99),
) -> list[dict[str, torch.Tensor]]:
    """``n`` members of ``profile`` (parameter tensors ``(1, 1)``, grid step 1)."""
    out = []
    for _ in range(n):
        if where == "interior":  # centre region: the member's zone and stencils stay inside
            off = rng.uniform(-0.5, 0.5, 2) * h
        else:  # anywhere on the grid, edges included
            off = rng.uniform(-0.5, 0.5, 2) * (m - 1) * 1.05
        if profile == "epl":
            e = rng.uniform(0, 0.28)
            phi = rng.uniform(0, np.pi)
            p = {
                "amp": 1.0,
                "gamma": rng.uniform(*gamma),
                "e1": e * np.cos(2 * phi),
                "e2": e * np.sin(2 * phi),
            }
        else:
            r_s = h * np.exp(rng.uniform(np.log(0.1), np.log(30)))
            p = {"r_s": r_s, "alpha_rs": 1.0}
            if profile == "tnfw":
                p["r_t"] = r_s * rng.uniform(1, 30)
        p["x"], p["y"] = off
        out.append({k: torch.tensor([[v]], dtype=F64) for k, v in p.items()})
    return out


def worst_ratios(
    profile: str, members, rho: float, orders: Sequence[int], spacing: int, m: int
) -> dict[int, float]:
    """Worst ratio (interpolation error / max ``|α|`` on ``r = r_c``) over ``members`` per order."""
    h = float(spacing)  # grid step = 1
    ax1 = torch.arange(m, dtype=F64) - (m - 1) / 2
    yy, xx = torch.meshgrid(ax1, ax1, indexing="ij")
    x, y = xx.reshape(1, -1), yy.reshape(1, -1)
    nodes = nearfar.node_indices(m, spacing)
    nd = torch.as_tensor(nodes)
    mats = {o: nearfar.interpolation_matrix(m, nodes, o, F64, "cpu") for o in orders}
    worst = dict.fromkeys(orders, 0.0)
    rc = rho * h
    for p in members:
        table = pair_sums.member_table(profile, p, 14)
        fx, fy, _ = pair_sums.far_sums(
            x, y, table, profile, torch.full((1, 1), 1.0 / rc**2, dtype=F64)
        )
        rows = [table[:, k, :, None] for k in range(table.shape[1])]
        ang = torch.arange(4, dtype=F64) * (np.pi / 2) + np.pi / 4
        cax, cay, _ = pair_sums.PAIR_FUNCTIONS[profile](
            rows[0] + rc * torch.cos(ang), rows[1] + rc * torch.sin(ang), rows
        )
        bound = float(torch.hypot(cax, cay).max())
        for o, lagrange in mats.items():
            err = 0.0
            for f in (fx, fy):
                g = f.reshape(m, m)
                err = max(err, float((lagrange @ g[nd][:, nd] @ lagrange.T - g).abs().max()))
            worst[o] = max(worst[o], err / bound)
    return worst


def class_rows(
    *,
    members: int,
    spacing: int,
    grid: int,
    safety: float,
    seed: int,
    rho_ladder: Sequence[float],
    gamma_edges: Sequence[float],
    only: tuple[str, int] | None = None,
) -> Iterator[tuple[str, str, int, int, list[float]]]:
    """``(where, profile, class row, order, C_p(ρ) on the ladder)`` for every class.

    The members of every class are drawn in table order from one generator seeded
    with ``seed``, so ``only=(where, index of the class)`` measures that one class with
    exactly the members of a full run (the other classes are drawn, not evaluated).
    """
    rng = np.random.default_rng(seed)
    classes = constant_classes(gamma_edges)
    for where in PLACEMENTS:
        m = grid_side(where, spacing, grid, rho_ladder)
        row_of: dict[str, int] = {}
        for index, (profile, gam) in enumerate(classes):
            draw = random_members(
                profile, members, float(spacing), m, rng, where, **({"gamma": gam} if gam else {})
            )
            row = row_of.get(profile, 0)
            row_of[profile] = row + 1
            if only is not None and only != (where, index):
                continue
            ratios = [worst_ratios(profile, draw, rho, ORDERS, spacing, m) for rho in rho_ladder]
            for order in ORDERS:
                yield where, profile, row, order, [safety * r[order] for r in ratios]


def measure_tables(*, seeds: Sequence[int], round_digits: int = 2, **kwargs: Any) -> dict[str, Any]:
    """``{where: {profile: {order: rows}}}``: the elementwise maximum over ``seeds`` of
    :func:`class_rows`, each value rounded to ``round_digits`` significant digits."""
    tables: dict[str, Any] = {}
    for seed in seeds:
        for where, profile, row, order, values in class_rows(seed=seed, **kwargs):
            rows = tables.setdefault(where, {}).setdefault(profile, {}).setdefault(str(order), [])
            while len(rows) <= row:
                rows.append([0.0] * len(values))
            rows[row] = [max(a, b) for a, b in zip(rows[row], values)]
    return {
        where: {
            p: {
                o: [[round_significant(v, round_digits) for v in r] for r in rows]
                for o, rows in by_order.items()
            }
            for p, by_order in by_profile.items()
        }
        for where, by_profile in tables.items()
    }


def round_significant(value: float, digits: int) -> float:
    """``value`` rounded to ``digits`` significant digits (as ``f"{value:.{digits}g}"``)."""
    return float(f"{value:.{digits}g}")
