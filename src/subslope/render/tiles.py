"""Tiles of a grid block for the near/far split: the block's rays cut into
``TILE × TILE`` tiles, the (tile, member) pairs whose near zone can reach a tile, the
exact near field summed on tiles, the exact far field in tiles whose ray map is rough,
and the distortion of displaced (multi-plane) rays. :mod:`subslope.render.nearfar` runs
the pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "GridBlock",
    "TILE",
    "ROW_SLOTS",
    "SMOOTH_DISTORTION",
    "MAX_DISTORTION",
    "far_on_tiles",
    "near_pairs",
    "near_on_tiles",
]


@dataclass(frozen=True)
class GridBlock:
    """A regular ``m × m`` image-plane grid stored row-major at ``[offset, offset + m²)``
    of the point axis: point ``(j, i)`` (row ↔ y) sits at ``((i − (m−1)/2)·step,
    (j − (m−1)/2)·step)`` arcsec before any foreground deflection."""

    offset: int
    m: int
    step: float


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
    (:func:`_tiled`). Returns ``(ax, ay, kappa)``, each ``(b, m²)``, and the κ sum
    ``(b,)`` over every tile point (padding points included)."""
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
        _untiled(full[2], b, m, TILE),
        full[2].reshape(b, -1).sum(1),
    )


#: Member slots per row of the near-field pass (:func:`near_on_tiles`).
ROW_SLOTS = 32
