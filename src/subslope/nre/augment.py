"""Symmetries of the training images used as data augmentation (``training.augment``).

The scene prior is isotropic: the lens and source orientations are uniform, the lens
centre, subhalo and line-of-sight positions are drawn from distributions symmetric under
rotations and reflections of the sky, and the pixel grid ``x_i = (i − (n−1)/2)·Δ`` maps
onto itself under the eight symmetries of the square (the dihedral group D₄). An image
``x`` and its image ``g·x`` under any of them therefore have the same likelihood for
every γ, ``p(g·x | γ) = p(x | γ)``, up to the orientation of the point-spread function,
which the transform rotates with the image. Training on ``g·x`` with a transform drawn
per image and per step multiplies the distinct images the network sees by up to eight
without one more simulation (docs/estimator.md, "Augmentation").

The transform is applied to the pre-processed input (after the input transform,
whitening and the θ_E mask), so the circular mask moves with the lens it is centred on.
"""

from __future__ import annotations

import torch
from torch import Tensor

from subslope.nre.training_config import AUGMENTATIONS

__all__ = ["AUGMENTATIONS", "N_DIHEDRAL", "dihedral", "random_dihedral", "step_generator"]

#: Order of the dihedral group of the square: 4 rotations, each with or without a flip.
N_DIHEDRAL = 8


def dihedral(x: Tensor, k: int) -> Tensor:
    """Element ``k`` (0…7) of D₄ applied to the last two axes of ``x``: a rotation by
    ``(k mod 4)·90°`` after a left–right flip when ``k ≥ 4``; ``k = 0`` is the identity."""
    if not 0 <= int(k) < N_DIHEDRAL:
        raise ValueError(f"dihedral element k must be in 0..{N_DIHEDRAL - 1}, got {k!r}")
    if x.shape[-1] != x.shape[-2]:
        raise ValueError(f"dihedral symmetries need square images, got shape {tuple(x.shape)}")
    if k >= 4:
        x = torch.flip(x, (-1,))
    return torch.rot90(x, int(k) % 4, (-2, -1))


def random_dihedral(
    x: Tensor, generator: torch.Generator, *, start: int = 0, total: int | None = None
) -> Tensor:
    """Every image of the batch ``x`` ``(B, ..., H, W)`` under its own element of D₄,
    drawn uniformly from ``generator`` (CPU); a new tensor, ``x`` untouched.

    ``x`` may be the rows ``start .. start + B`` of a batch of ``total`` images (one rank's
    share in data-parallel training): the elements are drawn for the whole batch and
    this share's are used, so every image gets the element one process would give it."""
    total = x.shape[0] if total is None else int(total)
    k = torch.randint(0, N_DIHEDRAL, (total,), generator=generator)
    k = k[start : start + x.shape[0]].to(x.device)
    out = torch.empty_like(x)
    for element in range(N_DIHEDRAL):
        rows = (k == element).nonzero(as_tuple=True)[0]
        if rows.numel():
            out[rows] = dihedral(x[rows], element)
    return out


def step_generator(seed: int, step: int) -> torch.Generator:
    """The generator of optimiser step ``step`` of a run seeded ``seed``: a function of
    the two numbers only, so a run resumed from a checkpoint draws the same transforms as
    an uninterrupted one, whatever the data loader's workers did."""
    return torch.Generator().manual_seed((int(seed) * 1_000_003 + int(step)) % 2**63)
