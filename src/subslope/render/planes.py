"""The planes of a render call's sub-batch: the members of a ragged population, and the
line-of-sight planes in front of and behind the lens plane, shared by the sub-batch's
images by rank (``docs/simulation.md``)."""

from __future__ import annotations

import numpy as np
import torch

from subslope.physics.raytrace import Plane
from subslope.ragged import pack_ragged
from subslope.render.counters import count_step
from subslope.render.populations import (
    PROFILE_KEYS,
    Population,
    flat_table,
    population_pass,
    select_systems,
)

__all__ = ["flat_members", "los_planes", "slice_ranks"]


def flat_members(pop, sel: np.ndarray) -> dict[str, np.ndarray | None]:
    """The parameters of members ``sel`` of a ragged population, flat."""
    return {
        kk: (None if getattr(pop, kk, None) is None else np.asarray(getattr(pop, kk))[sel])
        for kk in PROFILE_KEYS[pop.profile]
    }


def slice_ranks(sys_local: np.ndarray, z_h: np.ndarray, zl: np.ndarray, b: int):
    """Plane index of every LoS halo of a sub-batch when the slices of all its images
    share planes: an image's slices in front of its lens plane end at the same plane
    (right-aligned), those behind start at the same plane (left-aligned). Returns the
    halos' plane indices (front ``0 … F−1``, behind ``F … F+K−1``), ``F`` and ``K``."""
    keys = np.stack([sys_local.astype(np.float64), z_h], axis=1)
    pairs, inv = np.unique(keys, axis=0, return_inverse=True)  # image slices, by (image, z)
    img = pairs[:, 0].astype(np.int64)
    front = pairs[:, 1] < zl[img]
    rank = np.arange(img.size) - np.searchsorted(img, img)  # ascending z within the image
    n_front = np.bincount(img[front], minlength=b)
    f_max = int(n_front.max())
    behind = rank - n_front[img]
    plane = np.where(front, f_max - n_front[img] + rank, f_max + behind)
    k_max = int(behind[~front].max(initial=-1)) + 1
    return plane[inv.reshape(-1)], f_max, k_max


def los_planes(batch, los, lens_plane, zl: np.ndarray, zs: np.ndarray) -> list[Plane]:
    """The line-of-sight planes in front of and behind the lens plane, with the lens
    plane between them (an empty list when the sub-batch has no LoS halos).

    Each image's slices are planes of their own redshift; the images of a sub-batch share
    plane objects by rank (:func:`slice_ranks`), each plane with per-image redshifts and
    an ``active`` mask for images without a slice there, so that a sub-batch of ``b``
    images costs as many population passes as its image with the most slices."""
    if los is None:
        return []
    counts, sel = select_systems(los.counts, batch.idx)
    if counts.sum() == 0:
        return []
    settings, device, b = batch.settings, batch.device, batch.size
    sys_local = np.repeat(np.arange(b), counts)
    z_h = np.asarray(los.z, dtype=np.float64)[sel]
    bad = z_h >= zs[sys_local]
    if np.any(bad):
        j = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"los.z = {z_h[j]} is not in front of z_source = {zs[sys_local[j]]} "
            f"of system {int(batch.idx[sys_local[j]])}"
        )
    # one member table for every LoS halo of the sub-batch (plus a zero-amplitude
    # column for padding); each plane gathers its columns
    table_all = flat_table(
        los.profile, flat_members(los, sel), settings.n_terms, settings.dtype, device
    )
    n_los = table_all.shape[-1] - 1
    plane_of, f_max, k_max = slice_ranks(sys_local, z_h, zl, b)
    planes = []
    for k in range(f_max + k_max):
        on = np.flatnonzero(plane_of == k)
        c_slice = np.bincount(sys_local[on], minlength=b)
        # at least two member slots: the compiled kernels then keep one graph for every
        # plane (torch.compile specialises a dimension of size 1)
        cols, _ = pack_ragged(on, counts=c_slice, n_max=max(2, int(c_slice.max())), fill=n_los)
        pop = Population(
            los.profile,
            table_all[:, torch.as_tensor(cols, device=device)].permute(1, 0, 2).contiguous(),
            c_slice,
            batch.sheet[1],
            batch.members,
        )
        z_plane = zl.astype(np.float64).copy()  # inactive images: any redshift > 0
        z_plane[sys_local[on]] = z_h[on]

        def deflect(tx, ty, pop=pop):
            count_step("los")
            ax, ay, _ = population_pass(
                pop, tx, ty, settings, batch.kernels, batch.grid[2], batch.geometry
            )
            return ax, ay

        planes.append(Plane(z_plane, (deflect,), c_slice > 0))
    return planes[:f_max] + [Plane(zl, (lens_plane,), None)] + planes[f_max:]
