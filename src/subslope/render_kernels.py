"""Fused per-chunk kernels of the batched renderer (:mod:`subslope.render`).

A *chunk* is ``w`` members (``w`` a power of two) of a padded population with
parameters of shape ``(b, w, 1)``, evaluated against coordinates ``(b or 1, 1, P)``.
Each kernel returns the member sums, each ``(b, P)``:

- :func:`epl_chunk`: summed EPL deflection and, optionally, summed convergence
  (the convergence shares ``R^(1-gamma)`` with the deflection, so it costs one
  multiply and one sum when the deflection grid is the pixel grid);
- :func:`epl_kappa_chunk`: summed EPL convergence only.

The maths is :func:`subslope.profiles.epl.epl_deflection_and_convergence` itself (one
source of truth); the kernels only add the member sums.

Padding: padded members carry ``amp = 0`` (and benign ``gamma = 2``, ``e1 = e2 = 0``),
so they contribute exact zeros; no mask pass is needed.

Member sums use a fixed pairwise tree (``t[:, :w/2] + t[:, w/2:]`` repeated), i.e.
only element-wise additions. Zero members appended to a chunk (wider padding) leave
the tree sum bit-identical, and element-wise ops give the same bits whatever the
batch size, device thread split or reduction heuristics: this is what makes the
renderer batch-invariant.
"""

from __future__ import annotations

import torch
from torch import Tensor

from subslope.profiles.epl import epl_convergence, epl_deflection_and_convergence

__all__ = ["tree_sum_members", "tree_sum_last", "epl_chunk", "epl_kappa_chunk"]


def tree_sum_members(t: Tensor) -> Tensor:
    """Sum over axis 1 (a power-of-two length) by a fixed pairwise tree; ``(b, w, P) -> (b, P)``."""
    w = t.shape[1]
    while w > 1:
        w //= 2
        t = t[:, :w] + t[:, w:]
    return t[:, 0]


def tree_sum_last(t: Tensor) -> Tensor:
    """Sum over the last axis by a fixed pairwise tree (zero-padded to a power of two)."""
    n = t.shape[-1]
    w = 1
    while w < n:
        w *= 2
    if w != n:
        t = torch.nn.functional.pad(t, (0, w - n))
    while w > 1:
        w //= 2
        t = t[..., :w] + t[..., w:]
    return t[..., 0]


def epl_chunk(x: Tensor, y: Tensor, amp: Tensor, gamma: Tensor, e1: Tensor, e2: Tensor,
              cx: Tensor, cy: Tensor, n_terms: int, with_kappa: bool):
    """Summed EPL deflection (and convergence) of one chunk.

    ``x, y``: ``(b|1, 1, P)`` arcsec; parameters ``(b, w, 1)``; ``w`` a power of two.
    Returns ``(ax, ay, kappa)`` each ``(b, P)`` (``kappa`` is None unless ``with_kappa``).
    """
    ax, ay, kappa = epl_deflection_and_convergence(x, y, amp, gamma, e1, e2, cx, cy,
                                                   n_terms=n_terms, validate=False)
    kap = tree_sum_members(kappa) if with_kappa else None
    return tree_sum_members(ax), tree_sum_members(ay), kap


def epl_kappa_chunk(x: Tensor, y: Tensor, amp: Tensor, gamma: Tensor, e1: Tensor, e2: Tensor,
                    cx: Tensor, cy: Tensor) -> Tensor:
    """Summed EPL convergence of one chunk, ``(b, P)`` (shapes as :func:`epl_chunk`)."""
    return tree_sum_members(epl_convergence(x, y, amp, gamma, e1, e2, cx, cy, validate=False))
