"""Population passes: the summed deflection of a population of members (subhalos, the
halos of one line-of-sight plane) and its negative sheet.

A population of a sub-batch is a :class:`Population`, a padded member table
``(b, M, N)`` (:func:`subslope.physics.pairs.sums.member_table`; padded members have
zero amplitude). :func:`population_pass` sums it at the rays, directly in chunks of
:func:`subslope.render.settings.chunk_width` members or, for large populations, with
the near/far split of :mod:`subslope.render.nearfar`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from subslope.physics.pairs.registry import PAIR_PROFILES
from subslope.physics.pairs.sums import member_table, moments_centroid, sheet_centroid
from subslope.ragged import counts_to_offsets, pack_ragged
from subslope.render.counters import count_step
from subslope.render.kernels import FEW_MEMBERS, Kernels
from subslope.render.nearfar import split_pass
from subslope.render.settings import RenderSettings, chunk_width
from subslope.render.tiles import GridBlock

__all__ = [
    "PAD_VALUES",
    "PROFILE_KEYS",
    "SHEET_CENTRES",
    "Geometry",
    "Population",
    "flat_table",
    "main_lens_deflection",
    "pack_population",
    "population_pass",
    "profile_values",
    "select_systems",
    "use_split",
]


def select_systems(counts, idx) -> tuple[np.ndarray, np.ndarray]:
    """Counts of systems ``idx`` of a ragged population and the flat indices of their members."""
    counts_all = np.asarray(counts, dtype=np.int64)
    off = counts_to_offsets(counts_all)
    sel = (
        np.concatenate([np.arange(off[i], off[i + 1]) for i in idx])
        if len(idx)
        else np.zeros(0, np.int64)
    )
    return counts_all[idx], sel


#: Parameter keys of each profile's members and their padding values (the registry's).
PROFILE_KEYS = {name: p.keys for name, p in PAIR_PROFILES.items()}
PAD_VALUES = {key: value for p in PAIR_PROFILES.values() for key, value in p.padding.items()}


@dataclass
class Population:
    """A padded population of a sub-batch: its member table ``(b, M, N)``
    (:func:`subslope.physics.pairs.sums.member_table`; padded members have zero amplitude)
    and where its negative sheet is centred (:data:`SHEET_CENTRES`). ``members=False``
    keeps the sheet but drops the members' own deflections (the null test of a scene
    with its halos removed and their sheets kept)."""

    profile: str
    table: Tensor
    counts: np.ndarray
    sheet_centre: str = "origin"
    members: bool = True

    def __post_init__(self) -> None:
        if self.sheet_centre not in SHEET_CENTRES:
            raise ValueError(
                f"sheet_centre must be one of {SHEET_CENTRES}, got {self.sheet_centre!r}"
            )


#: Where a population's negative sheet is centred: ``origin`` (the plane's origin, the
#: reference analysis) or ``mass_centroid`` (the κ-weighted centre of the population
#: over the pixel-centre rays of its plane, :func:`subslope.physics.pairs.sums.sheet_centroid`).
SHEET_CENTRES = ("origin", "mass_centroid")


def profile_values(profile: str, flat: dict[str, np.ndarray]):
    """``(key, float64 values)`` of every parameter of ``profile``; a clear error for a
    missing one."""
    for key in PROFILE_KEYS[profile]:
        if flat.get(key) is None:
            raise ValueError(f"population of profile {profile!r} has no {key!r} values")
        yield key, np.asarray(flat[key], dtype=np.float64)


def pack_population(
    profile: str,
    flat: dict[str, np.ndarray],
    counts: np.ndarray,
    n_terms: int,
    dtype,
    device,
    sheet_centre: str = "origin",
    members: bool = True,
) -> Population:
    n_pad = max(1, int(counts.max()) if counts.size else 0)
    params = {}
    for key, vals in profile_values(profile, flat):
        arr, _ = pack_ragged(vals, counts=counts, n_max=n_pad, fill=PAD_VALUES[key])
        params[key] = torch.as_tensor(arr, dtype=dtype, device=device)
    table = member_table(profile, params, n_terms)
    return Population(profile, table, counts, sheet_centre, members)


def flat_table(profile: str, flat: dict[str, np.ndarray], n_terms: int, dtype, device) -> Tensor:
    """Member table ``(M, n + 1)`` of ``n`` members given as flat arrays, plus one padding
    member (zero amplitude) as the last column."""
    params = {
        key: torch.as_tensor(np.append(vals, PAD_VALUES[key]), dtype=dtype, device=device)[None, :]
        for key, vals in profile_values(profile, flat)
    }
    return member_table(profile, params, n_terms)[0]


@dataclass(frozen=True)
class Geometry:
    """Layout of the points of a render call: regular grid blocks (sub-pixels, then
    pixel centres when supersampled), the block of pixel centres, the undeflected
    grid ``(1, P)`` and whether the rays on this plane are displaced from it."""

    blocks: tuple[GridBlock, ...]
    sheet_block: int
    base: tuple[Tensor, Tensor]
    displaced: bool = True


def use_split(counts: np.ndarray, settings: RenderSettings, geometry: Geometry | None) -> bool:
    """Whether a population of these per-image member ``counts`` is summed with the
    near/far split (``settings.population``)."""
    if geometry is None or settings.population == "direct":
        return False
    return settings.population == "split" or int(counts.max()) >= settings.split_min_members


def population_pass(
    pop: Population,
    x: Tensor,
    y: Tensor,
    settings: RenderSettings,
    kernels: Kernels,
    n_pix: int,
    geometry: Geometry | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Summed deflection at (x, y) ``(b, P_all)`` and the negative-sheet κ ``(b, 1)``
    (minus the mean summed κ over the last ``n_pix`` points, the pixel-centre rays);
    the sheet is centred as ``pop.sheet_centre`` says.

    With ``geometry`` and a population large enough (``settings.population``), the
    near/far split of :mod:`subslope.render.nearfar`; otherwise the direct sum in chunks of
    :func:`chunk_width` members.
    """
    n_all = x.shape[-1]
    centroid = pop.sheet_centre == "mass_centroid"
    if use_split(pop.counts, settings, geometry):
        count_step("split")
        out = split_pass(
            pop.table,
            pop.profile,
            x,
            y,
            list(geometry.blocks),
            geometry.sheet_block,
            spacing=settings.split_spacing * settings.pixel_scale,
            order=settings.split_order,
            tolerance=settings.split_tolerance,
            displaced=geometry.displaced,
            base=geometry.base,
            kernels=(kernels.far, kernels.near, kernels.peaks),
            max_elements=settings.max_elements,
            moments=centroid,
        )
        ax, ay, k_sum = out
        if centroid:
            k0, kx, ky = k_sum
            cx, cy = moments_centroid(k0, kx, ky)
            return _with_sheet(pop, ax, ay, -(k0 / n_pix), x - cx, y - cy)
        return _with_sheet(pop, ax, ay, -(k_sum / n_pix)[:, None], x, y)
    n = pop.table.shape[-1]
    if n < FEW_MEMBERS and kernels.compiled and pop.members:
        return kernels.few_sheet(x, y, pop.table, pop.profile, n_pix, centroid)
    w = chunk_width(settings, n_all, kernels.compiled)
    ax = ay = kap = None
    for start in range(0, n, w):
        dax, day, dk = kernels.direct(
            x, y, pop.table[:, :, start : start + w].contiguous(), pop.profile, True
        )
        if ax is None:
            ax, ay, kap = dax, day, dk
        else:
            ax, ay, kap = ax + dax, ay + day, kap + dk
    k_sheet = -(kap[:, n_all - n_pix :].sum(-1) / n_pix)[:, None]
    if centroid:
        cx, cy = sheet_centroid(
            kap[:, n_all - n_pix :], x[:, n_all - n_pix :], y[:, n_all - n_pix :]
        )
        return _with_sheet(pop, ax, ay, k_sheet, x - cx, y - cy)
    return _with_sheet(pop, ax, ay, k_sheet, x, y)


def _with_sheet(pop: Population, ax, ay, k_sheet, dx, dy) -> tuple[Tensor, Tensor, Tensor]:
    """The members' deflection (unless ``pop.members`` is off) plus the sheet's,
    ``k_sheet · (dx, dy)`` about its centre."""
    if not pop.members:
        return k_sheet * dx, k_sheet * dy, k_sheet
    return ax + k_sheet * dx, ay + k_sheet * dy, k_sheet


def main_lens_deflection(
    x: Tensor, y: Tensor, table: Tensor, kernels: Kernels
) -> tuple[Tensor, Tensor]:
    """Main-lens EPL deflection ``(b, P)`` from its one-member table ``(b, M, 1)``
    (``n_terms_main`` series terms; the same arithmetic as
    :func:`subslope.physics.profiles.epl.epl_deflection`, as one fused kernel)."""
    ax, ay, _ = kernels.few(x, y, table, "epl", False)
    return ax, ay
