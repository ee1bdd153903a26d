r"""Near/far split of a population pass: exact near field, interpolated far field.

A population of ``N`` members (subhalos) deflects the rays of ``P`` points (pixels).
The direct sum costs ``N·P`` pair evaluations. Each member's deflection is split with
the partition of unity of :func:`subslope.physics.pairs.sums.split_weight`:

.. math::

    \alpha_i = \underbrace{\alpha_i\,W(|x - c_i| / r_{c,i})}_{\text{far: smooth everywhere}}
             + \underbrace{\alpha_i\,[1 - W(|x - c_i| / r_{c,i})]}_{\text{near: zero beyond }
             r_{c,i}},

the particle–particle/particle–mesh idea of N-body codes (Hockney & Eastwood 1988,
ch. 8) with a compactly supported near part.

* **Far field** ``Σ_i α_i W_i`` (and ``Σ_i κ_i W_i``) is smooth, so it is evaluated at
  the rays of a coarse subset of the points only (*nodes*: every ``S``-th point of each
  regular image-plane grid, both edges included; ``S·step = h``) and interpolated to
  all points by tensor-product Lagrange interpolation of order ``p`` in the grid
  indices (a separable ``L F Lᵀ`` product). The rays are a smooth function of the
  image-plane position (the identity for one plane; the foreground line-of-sight
  deflections in a multi-plane scene), so the far field is smooth in those indices
  too. Cost: ``N · (m/S)²`` pairs.
* **Split radius per member.** The interpolation error of one member's far field is
  ``≤ C_p(ρ)·max|α_i(r_c)|`` with ``ρ = r_c/h`` (:data:`ERROR_CONSTANTS`, measured by
  ``benchmarks/split_constants.py`` per profile and, for EPL members, per class of γ:
  :data:`EPL_GAMMA_EDGES`; steep members need larger constants than γ ≈ 2 ones).
  Each member gets the smallest ``ρ`` of
  :data:`RHO_LADDER` that meets ``split_tolerance`` (:func:`member_rungs`): the many
  small subhalos get small near zones, the few massive ones large ones. The errors of
  nearby members add (measured: the image error grows ∝ N), so above
  :data:`REFERENCE_MEMBERS` members the per-member tolerance shrinks ∝ 1/N.
* **Near field** ``Σ_i α_i (1 − W_i)`` is exact: the grid is cut into ``TILE × TILE``
  tiles and each tile sums the members whose near zone can reach it
  (:func:`near_pairs`: one dense box-distance test). The (tile, member) pairs fill
  rows of :data:`ROW_SLOTS` member slots, one fused reduction for all rows
  (:func:`subslope.physics.pairs.sums.near_tile_sums`), whose sums are added into their
  tiles; points beyond a member's ``r_c`` get exactly zero from it. The image-plane position of a
  member is found by two fixed-point steps ``θ ← c_i + d(θ)`` (``d``: the rays'
  displacement from the regular grid). With displaced rays the reach is widened by the
  largest displacement gradient ``G`` over the tiles around the member
  (``|x_j − c_i| ≥ (1 − G)|θ_j − θ_i|``); a member with ``G >`` :data:`MAX_DISTORTION`
  (a cuspy foreground halo nearby) reaches every tile.
* **Rough ray maps.** Where the rays are strongly distorted (a tile's displacement
  gradient above :data:`SMOOTH_DISTORTION`, near a foreground halo's centre), the far
  field is evaluated at every point of the tile instead of interpolated.

The negative-sheet convergence needs ``Σ_pixels Σ_i κ_i`` at the pixel-centre rays: the
far part is the interpolation weights' column sums applied to the node values, the near
part the sum of the tile terms on the pixel-centre grid.

Errors of every setting (node spacing, order, tolerance) are measured against the
direct sum in ``docs/performance.md`` and held to the image budget by
``tests/test_accuracy_budget.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import torch
from torch import Tensor

from subslope.render.counters import count_step
from subslope.render.tiles import (
    MAX_DISTORTION,
    SMOOTH_DISTORTION,
    TILE,
    GridBlock,
    _image_position,
    _member_distortion,
    _replace_tiles,
    _tile_distortion,
    _tiled,
    far_on_tiles,
    near_on_tiles,
    near_pairs,
)

__all__ = [
    "RHO_LADDER",
    "EPL_GAMMA_EDGES",
    "ERROR_CONSTANTS",
    "EDGE_ERROR_CONSTANTS",
    "REFERENCE_MEMBERS",
    "interpolation_matrix",
    "node_indices",
    "member_rungs",
    "split_pass",
    "constant_class",
]


@lru_cache(maxsize=64)
def node_indices(m: int, spacing: int) -> tuple[int, ...]:
    """Grid indices of the nodes along an axis of ``m`` points: both ends and a
    near-uniform spacing ≤ ``spacing`` in between."""
    if m <= 1:
        return (0,)
    n = max(2, math.ceil((m - 1) / spacing) + 1)
    return tuple(int(v) for v in np.unique(np.rint(np.linspace(0, m - 1, n)).astype(int)))


@lru_cache(maxsize=64)
def _interpolation_matrix_np(m: int, nodes: tuple[int, ...], order: int) -> np.ndarray:
    t = np.asarray(nodes, dtype=np.float64)
    n = t.size
    p = min(order, n)
    L = np.zeros((m, n))
    for i in range(m):
        # the p nodes around i (centred stencil, shifted at the edges)
        k = int(np.searchsorted(t, i, side="right")) - p // 2
        k = min(max(k, 0), n - p)
        st = t[k : k + p]
        for a in range(p):
            others = np.delete(st, a)
            L[i, k + a] = np.prod((i - others) / (st[a] - others))
    return L


def interpolation_matrix(m: int, nodes: tuple[int, ...], order: int, dtype, device) -> Tensor:
    """Lagrange interpolation matrix ``(m, len(nodes))`` of order ``order`` (points per
    stencil) from node indices to every grid index (exact at the nodes; reproduces
    polynomials of degree ``order − 1``)."""
    return torch.as_tensor(_interpolation_matrix_np(m, nodes, order), dtype=dtype, device=device)


#: Ladder of split radii ρ = r_c / h (in node spacings) a member may get.
RHO_LADDER = (1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0, 12.0, 16.0, 24.0, 32.0)
#: Upper γ edges of the classes of EPL members with their own error constants (the
#: first class starts at γ = 1, the last ends at 3).
EPL_GAMMA_EDGES = (1.5, 1.8, 2.2, 2.5)


def _load_error_constants() -> tuple[dict, dict]:
    """The measured ``C_p(ρ)`` tables of ``split_constants.json`` (written by
    ``benchmarks/split_constants.py``, which records how), checked against the ladder
    and γ classes of this module."""
    import json
    from importlib import resources as importlib_resources

    path = importlib_resources.files("subslope") / "render" / "split_constants.json"
    doc = json.loads(path.read_text(encoding="utf-8"))
    if tuple(doc["rho_ladder"]) != RHO_LADDER or tuple(doc["epl_gamma_edges"]) != EPL_GAMMA_EDGES:
        raise RuntimeError(
            f"{path}: measured on another rho ladder or gamma classes than "
            "subslope.render.nearfar uses; rerun benchmarks/split_constants.py --out"
        )

    def tables(where: str) -> dict[str, dict[int, tuple[tuple[float, ...], ...]]]:
        return {
            profile: {
                int(order): tuple(tuple(row) for row in rows) for order, rows in by_order.items()
            }
            for profile, by_order in doc[where].items()
        }

    return tables("interior"), tables("edge")


#: ``C_p(ρ)``: bound on the far field's interpolation error of one member divided by
#: its largest ``|α|`` on the circle ``r = r_c``, on :data:`RHO_LADDER`, for a member
#: whose zone and stencils stay inside the grid; per profile and interpolation order
#: ``p``, one row per class (EPL: the γ classes of :data:`EPL_GAMMA_EDGES`).
#: :data:`EDGE_ERROR_CONSTANTS`: the same for members anywhere on the image, edges
#: included (one-sided stencils at the edges are less accurate). Both are measured data
#: (``split_constants.json``, :mod:`subslope.validation.split_constants`).
ERROR_CONSTANTS, EDGE_ERROR_CONSTANTS = _load_error_constants()


@lru_cache(maxsize=64)
def _constants(profile: str, order: int, edge: bool, dtype, device) -> Tensor:
    """:data:`ERROR_CONSTANTS` (or the edge ones) of a profile and order as a tensor
    ``(classes, len(RHO_LADDER))``."""
    return torch.as_tensor(
        (EDGE_ERROR_CONSTANTS if edge else ERROR_CONSTANTS)[profile][order],
        dtype=dtype,
        device=device,
    )


def constant_class(table: Tensor, profile: str) -> Tensor:
    """Row of the error-constant tables of each member ``(b, N)`` (long): the γ class
    for EPL (table row 8 is ``−(γ − 1)/2``), 0 otherwise."""
    if profile != "epl":
        return torch.zeros(table[:, 0].shape, dtype=torch.long, device=table.device)
    edges = torch.as_tensor(EPL_GAMMA_EDGES, dtype=table.dtype, device=table.device)
    return torch.bucketize(_epl_gamma(table).contiguous(), edges)


def _epl_gamma(table: Tensor) -> Tensor:
    """γ ``(b, N)`` of EPL members from their table (row 8 is ``−(γ − 1)/2``,
    :func:`subslope.physics.pairs.epl.epl_table`)."""
    return 1.0 - 2.0 * table[:, 8]


def _live(table: Tensor, profile: str) -> Tensor:
    """Members that are not padding (non-zero amplitude row), ``(b, N)`` bool."""
    from subslope.physics.pairs.sums import AMPLITUDE_ROW

    return table[:, AMPLITUDE_ROW[profile], :] != 0


def member_rungs(
    table: Tensor,
    profile: str,
    h: float,
    order: int,
    tolerance,
    peaks=None,
    half_width: float | None = None,
) -> Tensor:
    """Index into :data:`RHO_LADDER` of each member's split radius ``(b, N)`` (long).

    The smallest ρ with ``C_p(ρ)·max|α_i(r = ρh)| ≤ tolerance`` (arcsec), ``|α_i|``
    taken at 4 diagonal directions on the circle
    (:func:`subslope.physics.pairs.sums.circle_peaks`, or the compiled ``peaks``); ``C_p``
    from :data:`ERROR_CONSTANTS` when the member's zone and the stencils around it
    (``ρh + (p/2 + 1)h``) stay inside the field of half-width ``half_width`` (arcsec),
    else from :data:`EDGE_ERROR_CONSTANTS`; the largest rung when none qualifies.
    ``h``: node spacing (arcsec); ``tolerance``: a float or a tensor broadcasting
    against ``(b, N, L)``.
    """
    from subslope.physics.pairs.sums import circle_peaks

    kw = {"dtype": table.dtype, "device": table.device}
    rho = torch.as_tensor(RHO_LADDER, **kw)
    if profile not in ERROR_CONSTANTS or order not in ERROR_CONSTANTS[profile]:
        known = {p: sorted(v) for p, v in ERROR_CONSTANTS.items()}
        raise ValueError(
            f"no split error constants for profile {profile!r} and order {order}; known: {known}"
        )
    cls = constant_class(table, profile)
    c_in = _constants(profile, order, False, table.dtype, table.device)[cls]  # (b, N, L)
    c_edge = _constants(profile, order, True, table.dtype, table.device)[cls]
    if profile == "epl":
        # the EPL is scale-free, |α(λx)| = λ^(2−γ) |α(x)|: one circle, scaled to each radius
        one = (peaks or circle_peaks)(table, profile, rho[:1] * h)  # (b, N, 1)
        amax = one * torch.pow(rho / rho[0], (2.0 - _epl_gamma(table))[..., None])
    else:
        amax = (peaks or circle_peaks)(table, profile, rho * h)  # (b, N, L)
    if half_width is None:
        c = c_edge
    else:
        inset = half_width - torch.maximum(table[:, 0].abs(), table[:, 1].abs())  # (b, N)
        inside = inset[..., None] >= (rho + order / 2 + 1) * h
        c = torch.where(inside, c_in, c_edge)
    ok = c * amax <= tolerance
    ok[..., -1] = True
    return ok.to(torch.int8).argmax(-1)


#: Population size up to which ``split_tolerance`` is the per-member error target; a
#: population of N > this many members gets ``split_tolerance · REFERENCE_MEMBERS / N``.
REFERENCE_MEMBERS = 1000


@dataclass(frozen=True)
class _Pass:
    """What every grid block of one split pass shares."""

    table: Tensor
    profile: str
    inv_rc2: Tensor
    r_c: Tensor
    live: Tensor
    far_k: Any
    near_k: Any
    order: int
    spacing: float
    max_elements: int

    @property
    def b(self) -> int:
        return self.table.shape[0]

    @property
    def n(self) -> int:
        return self.table.shape[2]


def _far_field(p: _Pass, bx: Tensor, by: Tensor, blk: GridBlock):
    """Far field of every member at the block's nodes: ``(fx, fy, fk)`` ``(b, nodes)``,
    the node indices and the interpolation matrix."""
    m = blk.m
    nodes = node_indices(m, max(1, int(round(p.spacing / blk.step))))
    nd = torch.as_tensor(nodes, device=bx.device)
    flat_nodes = (nd[:, None] * m + nd[None, :]).reshape(-1)
    xn, yn = bx[:, flat_nodes], by[:, flat_nodes]
    fx = fy = fk = None
    # members per call: a call holds (b, nodes, members) pairs, b the images of the pass
    step_n = max(1, p.max_elements // max(1, xn.shape[0] * flat_nodes.numel()))
    for s in range(0, p.n, step_n):
        e = min(p.n, s + step_n)
        px, py, pk = p.far_k(
            xn, yn, p.table[:, :, s:e].contiguous(), p.profile, p.inv_rc2[:, s:e].contiguous()
        )
        fx, fy, fk = (px, py, pk) if fx is None else (fx + px, fy + py, fk + pk)
    return fx, fy, fk, nodes, interpolation_matrix(m, nodes, p.order, bx.dtype, bx.device)


def _rough_tiles(p: _Pass, rough: Tensor, tx_all: Tensor, ty_all: Tensor, nt: int):
    """The exact far field ``(ex, ey, ek)`` at every point of the tiles ``rough``."""
    tx, ty = tx_all[rough], ty_all[rough]
    img = torch.div(rough, nt * nt, rounding_mode="floor")
    ex = ey = ek = None
    step_r = max(1, p.max_elements // max(1, tx.numel()))
    for s0 in range(0, p.n, step_r):
        e0 = min(p.n, s0 + step_r)
        px, py, pk = far_on_tiles(
            p.far_k, tx, ty, p.table[:, :, s0:e0], p.profile, p.inv_rc2[:, s0:e0], img
        )
        ex, ey, ek = (px, py, pk) if ex is None else (ex + px, ey + py, ek + pk)
    return ex, ey, ek


def _near_radius(
    p: _Pass, blk: GridBlock, disp: tuple[Tensor, Tensor] | None, tile_g: Tensor | None
):
    """Image-plane grid position ``(v, u)`` of each member and the radius (in grid
    steps) within which its near field can reach a point."""
    margin = 0.75
    cx, cy = p.table[:, 0, :], p.table[:, 1, :]
    if disp is None:
        v, u = _image_position(cx, cy, blk, None, None)
        return v, u, p.r_c / blk.step + margin
    v, u = _image_position(cx, cy, blk, *disp)
    reach0 = p.r_c / blk.step + margin + 1.0
    grad = _member_distortion(tile_g, v, u, 2.0 * reach0, TILE)
    radius = torch.where(
        grad <= MAX_DISTORTION,
        reach0 / (1.0 - grad.clamp(max=MAX_DISTORTION)),
        torch.full_like(reach0, 4.0 * blk.m),
    )
    return v, u, radius


def _block_pass(
    p: _Pass,
    bx: Tensor,
    by: Tensor,
    blk: GridBlock,
    base: tuple[Tensor, Tensor] | None,
    with_sheet: bool,
    moments: bool = False,
):
    """Deflection ``(b, m²)`` of one grid block (far field interpolated, rough tiles
    exact, near field on tiles) and, for the sheet block, its κ sum ``(b,)``; with
    ``moments``, ``(Σκ, Σκx, Σκy)`` ``(b, 1)`` each over the block's rays in its place."""
    b, m = p.b, blk.m
    fx, fy, fk, nodes, lagrange = _far_field(p, bx, by, blk)
    nn = len(nodes)

    def interp(v):
        return (lagrange @ v.reshape(b, nn, nn) @ lagrange.T).reshape(b, m * m)

    acc_x, acc_y = interp(fx), interp(fy)
    k_sum = kmap = None
    if with_sheet:
        w = lagrange.sum(0)
        k_sum = ((fk.reshape(b, nn, nn) * w[:, None]) * w[None, :]).sum((1, 2))
        kmap = interp(fk) if moments else None
    nt = -(-m // TILE)
    tx_all, ty_all = _tiled(bx, m, TILE, 1e4), _tiled(by, m, TILE, 1e4)
    tile_g = disp = None
    if base is not None:
        sl = slice(blk.offset, blk.offset + m * m)
        disp = (base[0][:, sl] - bx, base[1][:, sl] - by)
        tile_g = _tile_distortion(*disp, blk, TILE)
        rough = torch.nonzero(tile_g.reshape(-1) > SMOOTH_DISTORTION).reshape(-1)
        if rough.numel():
            # the ray map is not smooth there (a foreground halo's centre): the far field
            # is evaluated at every point of those tiles instead of interpolated
            count_step("split_rough_tiles", rough.numel())
            ex, ey, ek = _rough_tiles(p, rough, tx_all, ty_all, nt)
            acc_x = _replace_tiles(acc_x, rough, ex, b, m)
            acc_y = _replace_tiles(acc_y, rough, ey, b, m)
            if with_sheet:
                kap_i = interp(fk)
                kap_r = _replace_tiles(kap_i, rough, ek, b, m)
                k_sum = k_sum + (kap_r - kap_i).sum(1)
                kmap = kap_r if moments else None
    v, u, radius = _near_radius(p, blk, disp, tile_g)
    tiles, mem = near_pairs(v, u, radius, p.live, nt, TILE)
    if tiles.numel():
        ox, oy, okmap, ok_ = near_on_tiles(
            p.near_k, p.table, p.profile, p.inv_rc2, tiles, mem, tx_all, ty_all, m, p.max_elements
        )
        acc_x = acc_x + ox
        acc_y = acc_y + oy
        if with_sheet:
            k_sum = k_sum + ok_
            kmap = kmap + okmap if moments else None
    if moments and with_sheet:
        k_sum = (
            kmap.sum(-1, keepdim=True),
            (kmap * bx).sum(-1, keepdim=True),
            (kmap * by).sum(-1, keepdim=True),
        )
    return acc_x, acc_y, k_sum


def split_pass(
    table: Tensor,
    profile: str,
    x: Tensor,
    y: Tensor,
    blocks: list[GridBlock],
    sheet_block: int,
    *,
    spacing: float,
    order: int,
    tolerance: float,
    displaced: bool,
    base: tuple[Tensor, Tensor] | None,
    kernels,
    max_elements: int,
    moments: bool = False,
):
    """Near/far population pass. Returns ``(alpha_x, alpha_y, kappa_sum)``.

    ``table``: ``(b, M, N)`` member table (:func:`subslope.physics.pairs.sums.member_table`);
    ``x, y``: rays ``(b, P)`` on the population's plane, laid out as ``blocks``;
    ``sheet_block``: index of the pixel-centre block whose κ sum the sheet needs;
    ``spacing``: node spacing ``h`` (arcsec; rounded to whole grid steps per block);
    ``order``: Lagrange stencil points per axis (``p``); ``tolerance``: far-field error
    target per member (arcsec; sets each member's ``r_c``, :func:`member_rungs`);
    ``displaced``: the rays are not the regular grids (multi-plane), then
    ``base = (x0, y0)`` ``(1, P)`` are the undeflected grids; ``kernels``:
    ``(far_sums, near_tile_sums, circle_peaks)`` callables (compiled or eager,
    :mod:`subslope.physics.pairs.sums`); ``max_elements``: bound on members × points per call.

    Returns ``alpha_x, alpha_y`` ``(b, P)`` (arcsec; no sheet) and ``kappa_sum`` ``(b,)``:
    ``Σ_{pixel-centre rays} Σ_i κ_i``; with ``moments`` instead the tuple
    ``(Σκ, Σκx, Σκy)`` ``(b, 1)`` each over those rays (the sheet centroid's moments).
    """
    far_k, near_k, *rest = kernels
    peaks_k = rest[0] if rest else None
    dtype, device = x.dtype, x.device
    half = 0.5 * (blocks[0].m - 1) * blocks[0].step
    live = _live(table, profile)
    # the interpolation errors of nearby members add: above REFERENCE_MEMBERS members
    # the per-member tolerance shrinks in proportion
    n_live = live.sum(1, keepdim=True).clamp(min=1).to(dtype)
    tol = tolerance * torch.clamp(REFERENCE_MEMBERS / n_live, max=1.0)[..., None]  # (b, 1, 1)
    rungs = member_rungs(table, profile, spacing, order, tol, peaks_k, half)  # (b, N)
    rho = torch.as_tensor(RHO_LADDER, dtype=dtype, device=device)[rungs]
    r_c = rho * spacing
    p = _Pass(
        table, profile, 1.0 / (r_c * r_c), r_c, live, far_k, near_k, order, spacing, max_elements
    )
    outs_x, outs_y = [], []
    k_sum = None
    for g, blk in enumerate(blocks):
        sl = slice(blk.offset, blk.offset + blk.m * blk.m)
        ax, ay, ks = _block_pass(
            p,
            x[:, sl].contiguous(),
            y[:, sl].contiguous(),
            blk,
            base if displaced else None,
            g == sheet_block,
            moments,
        )
        outs_x.append(ax)
        outs_y.append(ay)
        k_sum = ks if g == sheet_block else k_sum
    if blocks[-1].offset + blocks[-1].m ** 2 != x.shape[1]:
        raise ValueError(
            f"grid blocks cover {blocks[-1].offset + blocks[-1].m ** 2} points, rays have "
            f"{x.shape[1]}"
        )
    return torch.cat(outs_x, 1), torch.cat(outs_y, 1), k_sum
