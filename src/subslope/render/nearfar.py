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

__all__ = [
    "GridBlock",
    "RHO_LADDER",
    "ERROR_CONSTANTS",
    "EDGE_ERROR_CONSTANTS",
    "interpolation_matrix",
    "node_indices",
    "member_rungs",
    "split_pass",
    "TILE",
    "constant_class",
    "near_pairs",
    "near_on_tiles",
    "far_on_tiles",
]


@dataclass(frozen=True)
class GridBlock:
    """A regular ``m × m`` image-plane grid stored row-major at ``[offset, offset + m²)``
    of the point axis: point ``(j, i)`` (row ↔ y) sits at ``((i − (m−1)/2)·step,
    (j − (m−1)/2)·step)`` arcsec before any foreground deflection."""

    offset: int
    m: int
    step: float


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


#: Side of the near-field tiles, in grid points.
TILE = 8


def _image_position(cx: Tensor, cy: Tensor, blk: GridBlock, dx: Tensor | None, dy: Tensor | None):
    """Continuous grid coordinates ``(v, u)`` ``(b, N)`` (row, column) of the image-plane
    position of each member: ``θ = c + d(θ)`` by two fixed-point steps with ``d`` the
    rays' displacement from the regular grid (nearest point), or ``θ = c``."""
    half = (blk.m - 1) / 2.0
    tx, ty = cx, cy
    if dx is not None:
        for _ in range(2):
            j = torch.round(ty / blk.step + half).clamp(0, blk.m - 1).to(torch.long)
            i = torch.round(tx / blk.step + half).clamp(0, blk.m - 1).to(torch.long)
            flat = j * blk.m + i
            tx = cx + torch.gather(dx, 1, flat)
            ty = cy + torch.gather(dy, 1, flat)
    return ty / blk.step + half, tx / blk.step + half


def _tile_distortion(dx: Tensor, dy: Tensor, blk: GridBlock, tile: int) -> Tensor:
    """Largest displacement gradient per tile, ``(b, n_t, n_t)`` (dimensionless: arcsec
    of relative ray displacement per arcsec of image-plane separation), from finite
    differences of the displacement ``(dx, dy)`` ``(b, m²)`` between neighbouring points."""
    m = blk.m
    b = dx.shape[0]
    g = torch.zeros(b, m, m, dtype=dx.dtype, device=dx.device)
    for d in (dx.reshape(b, m, m), dy.reshape(b, m, m)):
        gv = d.diff(dim=1).abs()
        gu = d.diff(dim=2).abs()
        g[:, 1:, :] = torch.maximum(g[:, 1:, :], gv)
        g[:, :-1, :] = torch.maximum(g[:, :-1, :], gv)
        g[:, :, 1:] = torch.maximum(g[:, :, 1:], gu)
        g[:, :, :-1] = torch.maximum(g[:, :, :-1], gu)
    nt = -(-m // tile)
    g = torch.nn.functional.pad(g, (0, nt * tile - m, 0, nt * tile - m))
    return g.reshape(b, nt, tile, nt, tile).amax((2, 4)) / blk.step


def _member_distortion(tile_g: Tensor, v: Tensor, u: Tensor, reach: Tensor, tile: int) -> Tensor:
    """Largest displacement gradient over the tiles within ``reach`` grid steps of each
    member (``(b, N)``), from the per-tile maxima ``tile_g`` ``(b, n_t, n_t)``: a max
    filter per distinct reach (in tiles), read at the member's tile."""
    b, nt, _ = tile_g.shape
    k = torch.ceil(reach / tile).to(torch.long) + 1  # tiles
    row = torch.floor(v / tile).to(torch.long).clamp(0, nt - 1)
    col = torch.floor(u / tile).to(torch.long).clamp(0, nt - 1)
    out = torch.zeros_like(v)
    for kk in torch.unique(k).tolist():
        w = min(2 * kk + 1, 2 * nt + 1)
        pooled = torch.nn.functional.max_pool2d(tile_g[:, None], w, stride=1, padding=w // 2)[:, 0]
        sel = k == kk
        val = pooled[torch.arange(b, device=v.device)[:, None].expand_as(row), row, col]
        out = torch.where(sel, val, out)
    return out


#: Tiles whose rays are distorted by more than this gradient get the exact far field.
SMOOTH_DISTORTION = 0.02
#: Members whose rays are distorted by more than this gradient (a cuspy foreground halo
#: nearby) are not split: they are evaluated at every point of the grid.
MAX_DISTORTION = 0.25


def far_on_tiles(
    far_k, tx: Tensor, ty: Tensor, table: Tensor, profile: str, inv_rc2: Tensor, img: Tensor
):
    """Exact far field ``(T, Q)`` at the points of tiles ``tx, ty`` ``(T, Q)`` of images
    ``img`` ``(T,)`` (members of image ``img[t]`` only)."""
    outs = [[], [], []]
    for k in torch.unique(img).tolist():
        sel = img == k
        fx, fy, fk = far_k(
            tx[sel].reshape(1, -1),
            ty[sel].reshape(1, -1),
            table[k : k + 1].contiguous(),
            profile,
            inv_rc2[k : k + 1].contiguous(),
        )
        for o, f in zip(outs, (fx, fy, fk)):
            o.append((sel, f.reshape(-1, tx.shape[1])))
    res = []
    for o in outs:
        full = tx.new_zeros(tx.shape)
        for sel, f in o:
            full[sel] = f
        res.append(full)
    return res


def near_pairs(v: Tensor, u: Tensor, radius: Tensor, live: Tensor, n_tiles: int, tile: int):
    """(tile, member) pairs of every live member and every tile whose box comes within
    ``radius`` grid steps of the member's grid position ``(v, u)``.

    Inputs ``(b, N)``; tiles of image ``k`` are numbered ``k·n_tiles² + J·n_tiles + I``
    (tile ``J`` holds grid rows ``[J·t, (J+1)·t)``). Returns ``(tiles, members)``,
    ``(n_pairs,)`` long tensors sorted by tile (then member); ``members`` index the
    flattened ``(b·N)`` members. One dense ``(b, n_t, n_t, N)`` test of the box
    distances: no per-member loops, no host round trip but the final ``nonzero``.
    """
    b, n = v.shape
    lo = torch.arange(n_tiles, dtype=v.dtype, device=v.device) * tile - 0.5  # box [lo, lo + t]
    hi = lo + tile

    def gap(c: Tensor) -> Tensor:  # (b, n_t, N): distance from c to each box along one axis
        c = c[:, None, :]
        return torch.clamp(
            torch.maximum(lo[None, :, None] - c, c - hi[None, :, None]), min=0.0
        ).square_()

    r2 = torch.where(live, radius * radius, torch.full_like(radius, -1.0))
    near = gap(v)[:, :, None, :] + gap(u)[:, None, :, :] <= r2[:, None, None, :]
    idx = torch.nonzero(near)  # lexicographic: image, J, I, member
    tiles = (idx[:, 0] * n_tiles + idx[:, 1]) * n_tiles + idx[:, 2]
    return tiles, idx[:, 0] * n + idx[:, 3]


def _tiled(v: Tensor, m: int, tile: int, fill: float) -> Tensor:
    """``(b, m²)`` block values → ``(b·n_t², tile²)`` tiles (padded with ``fill``)."""
    b = v.shape[0]
    nt = -(-m // tile)
    img = torch.nn.functional.pad(
        v.reshape(b, m, m), (0, nt * tile - m, 0, nt * tile - m), value=fill
    )
    return (
        img.reshape(b, nt, tile, nt, tile).permute(0, 1, 3, 2, 4).reshape(b * nt * nt, tile * tile)
    )


def _replace_tiles(v: Tensor, tiles: Tensor, vals: Tensor, b: int, m: int) -> Tensor:
    """``(b, m²)`` block values with tiles ``tiles`` replaced by ``vals`` ``(T, TILE²)``."""
    t = _tiled(v, m, TILE, 0.0)
    t[tiles] = vals
    return _untiled(t, b, m, TILE)


def _untiled(t: Tensor, b: int, m: int, tile: int) -> Tensor:
    nt = -(-m // tile)
    img = t.reshape(b, nt, nt, tile, tile).permute(0, 1, 3, 2, 4).reshape(b, nt * tile, nt * tile)
    return img[:, :m, :m].reshape(b, m * m)


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


def near_on_tiles(
    near_k,
    table: Tensor,
    profile: str,
    inv_rc2: Tensor,
    tiles: Tensor,
    mem: Tensor,
    tx_all: Tensor,
    ty_all: Tensor,
    m: int,
    max_elements: int,
):
    """Near field of the (tile, member) pairs on one ``m × m`` block.

    The members of each tile fill rows of :data:`ROW_SLOTS` slots (the last row of a
    tile padded with a zero-weight slot), so the kernel
    (:func:`subslope.physics.pairs.sums.near_tile_sums`) sees one ``(rows, TILE², ROW_SLOTS)``
    problem and padding costs at most one partial row per tile; the rows' sums are
    added into their tiles. ``tx_all, ty_all``: the block's rays as tiles
    (:func:`_tiled`). Returns ``(ax, ay)`` ``(b, m²)`` and the κ sum ``(b,)``."""
    b, n_rows, n = table.shape
    device, dtype = tx_all.device, tx_all.dtype
    nt = -(-m // TILE)
    n_all = b * nt * nt
    w = ROW_SLOTS
    counts = torch.bincount(tiles, minlength=n_all)
    rows_per = (counts + (w - 1)) // w
    row_start = torch.cumsum(rows_per, 0) - rows_per
    slot = torch.arange(tiles.numel(), device=device) - (torch.cumsum(counts, 0) - counts)[tiles]
    n_r = int(rows_per.sum())
    pos = torch.full((n_r, w), b * n, dtype=torch.long, device=device)  # b·n: the padding column
    pos[row_start[tiles] + torch.div(slot, w, rounding_mode="floor"), slot % w] = mem
    tile_of_row = torch.repeat_interleave(torch.arange(n_all, device=device), rows_per)
    flat_tab = torch.cat([table.permute(1, 0, 2).reshape(n_rows, b * n), table[0, :, :1]], 1)
    flat_irc = torch.cat([inv_rc2.reshape(-1), inv_rc2.new_zeros(1)])
    mask_all = torch.cat(
        [torch.ones(b * n, dtype=dtype, device=device), torch.zeros(1, dtype=dtype, device=device)]
    )
    q = TILE * TILE
    full = torch.zeros(3, n_all, q, dtype=dtype, device=device)
    step = max(1, max_elements // (q * w))
    for r0 in range(0, n_r, step):
        p = pos[r0 : r0 + step]
        t = tile_of_row[r0 : r0 + step]
        fp = p.reshape(-1)
        out = near_k(
            tx_all[t],
            ty_all[t],
            torch.index_select(flat_tab, 1, fp).reshape(n_rows, *p.shape),
            profile,
            flat_irc.index_select(0, fp).reshape(p.shape),
            mask_all.index_select(0, fp).reshape(p.shape),
        )
        full.index_add_(1, t, torch.stack(out))
    return (
        _untiled(full[0], b, m, TILE),
        _untiled(full[1], b, m, TILE),
        full[2].reshape(b, -1).sum(1),
    )


#: Population size up to which ``split_tolerance`` is the per-member error target; a
#: population of N > this many members gets ``split_tolerance · REFERENCE_MEMBERS / N``.
REFERENCE_MEMBERS = 1000

#: Member slots per row of the near-field pass (:func:`near_on_tiles`).
ROW_SLOTS = 32


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
    step_n = max(1, p.max_elements // max(1, flat_nodes.numel()))
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
):
    """Deflection ``(b, m²)`` of one grid block (far field interpolated, rough tiles
    exact, near field on tiles) and, for the sheet block, its κ sum ``(b,)``."""
    b, m = p.b, blk.m
    fx, fy, fk, nodes, lagrange = _far_field(p, bx, by, blk)
    nn = len(nodes)

    def interp(v):
        return (lagrange @ v.reshape(b, nn, nn) @ lagrange.T).reshape(b, m * m)

    acc_x, acc_y = interp(fx), interp(fy)
    k_sum = None
    if with_sheet:
        w = lagrange.sum(0)
        k_sum = ((fk.reshape(b, nn, nn) * w[:, None]) * w[None, :]).sum((1, 2))
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
                k_sum = k_sum + (_replace_tiles(kap_i, rough, ek, b, m) - kap_i).sum(1)
    v, u, radius = _near_radius(p, blk, disp, tile_g)
    tiles, mem = near_pairs(v, u, radius, p.live, nt, TILE)
    if tiles.numel():
        ox, oy, ok_ = near_on_tiles(
            p.near_k, p.table, p.profile, p.inv_rc2, tiles, mem, tx_all, ty_all, m, p.max_elements
        )
        acc_x = acc_x + ox
        acc_y = acc_y + oy
        if with_sheet:
            k_sum = k_sum + ok_
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
    ``Σ_{pixel-centre rays} Σ_i κ_i``.
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
