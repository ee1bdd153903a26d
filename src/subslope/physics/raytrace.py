"""Single- and multi-plane lens equation.

A *deflector* is any callable ``(x, y) -> (ax, ay)`` on angular coordinates in
arcsec: typically ``functools.partial`` of a profile deflection with its parameters
bound, or a closure around a population pass (:func:`subslope.render.populations.population_pass`).

Single plane
------------
``beta = theta - sum_k alpha_k(theta)`` (:func:`ray_shoot`).

Multi-plane (flat FRW, comoving transverse coordinates)
-------------------------------------------------------
Let ``chi_i`` be the comoving distance to plane ``i`` (planes ordered by redshift,
``0 < z_1 <= z_2 <= ... < z_s``).  Between planes a back-traced ray is a straight
line in comoving transverse coordinates, and at plane ``i`` its direction turns by
the *physical* deflection ``alpha_hat_i``.  Hence (Blandford & Narayan 1986;
Schneider, Ehlers & Falco 1992 ch. 9; Petkova, Metcalf & Giocoli 2014, eqs. 3-6;
McCully et al. 2014, eq. 1)::

    x_j      = chi_j theta - sum_{i<j} (chi_j - chi_i) alpha_hat_i(theta_i),
    theta_j  = x_j / chi_j,
    beta     = theta - sum_{i: z_i < z_s} (chi_s - chi_i) / chi_s * alpha_hat_i(theta_i).

In a flat universe ``chi_j - chi_i = T_ij = (1 + z_j) D_A(z_i, z_j)`` (the comoving
transverse distance lenstronomy steps with).  It is evaluated with the O(n)
recursion (ray position at the previous plane ``p`` and ray direction ``a``)::

    theta_j = (chi_p / chi_j) theta_p + ((chi_j - chi_p) / chi_j) a,   a <- a -
    alpha_hat_j(theta_j),

starting from ``chi_p = 0``, ``a = theta``; the coefficients are exactly ``(0, 1)``
for the first plane and ``(1, 0)`` for a plane at the same redshift as the previous
one, so a single plane, or several planes at one redshift, give bit-for-bit the
single-plane lens equation.

Deflection convention (lenstronomy's ``MultiPlaneBase``): the parameters of every
plane give the *reduced* deflection ``alpha_i`` that the plane would produce for a
source at the convention redshift ``z_c`` (default: each system's own ``z_source``),
``alpha_i = D_A(z_i, z_c) / D_A(z_c) * alpha_hat_i``.  Internally
``alpha_hat_i = alpha_i * chi_c / (chi_c - chi_i)`` (lenstronomy's
``_reduced2physical_factor = D_s / D_ds``).  With ``z_c = z_source`` the source
equation above is simply ``beta = theta - sum_i alpha_i(theta_i)``, which is how it is
evaluated (no multiply-divide round trip).

Batching: plane redshifts, ``z_source`` and the optional per-plane ``active`` masks
may be per system (``(B,)``); all distance factors then become ``(B, 1)`` tensors.
For every system the *active* planes must be in non-decreasing redshift order.  When
the order of a plane relative to another depends on the system (fixed LoS slices vs
a per-system ``z_lens``), pass such slices twice, once in front of the lens plane
with ``active = z_slice < z_lens`` and once behind it with ``active = z_slice >=
z_lens`` (an inactive plane is still evaluated but contributes exactly nothing).

Only flat cosmologies are supported (``cosmo.Ok0 == 0``; Planck18 is flat); the
distances are computed once per redshift in numpy float64 with astropy and cached.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "Deflector",
    "Plane",
    "PlaneGeometry",
    "comoving_distance",
    "deflection_sum",
    "multi_plane_ray_shoot",
    "plane_geometry",
    "ray_shoot",
]

Deflector = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]


# ------------------------------------------------------------------------ single plane
def deflection_sum(x: Tensor, y: Tensor, deflectors: Sequence[Deflector]) -> tuple[Tensor, Tensor]:
    """Sum of the deflections ``(ax, ay)`` [arcsec] of ``deflectors`` at ``(x, y)``.

    Summed in list order starting from the first deflector (no ``0 +``).  With no
    deflector, zeros shaped like ``x``.
    """
    total: tuple[Tensor, Tensor] | None = None
    for k, d in enumerate(deflectors):
        if not callable(d):
            raise ValueError(
                f"deflectors[{k}] must be callable (x, y) -> (ax, ay), got {type(d).__name__}"
            )
        dx, dy = d(x, y)
        total = (dx, dy) if total is None else (total[0] + dx, total[1] + dy)
    if total is None:
        return torch.zeros_like(x), torch.zeros_like(y)
    return total


def ray_shoot(x: Tensor, y: Tensor, deflectors: Sequence[Deflector]) -> tuple[Tensor, Tensor]:
    """Single-plane lens equation ``beta = theta - sum_k alpha_k(theta)``.

    ``x, y``: image-plane coordinates [arcsec], any shape the deflectors accept
    (``(B, P)`` by convention).  Returns source-plane ``(beta_x, beta_y)``.
    """
    ax, ay = deflection_sum(x, y, deflectors)
    return x - ax, y - ay


# --------------------------------------------------------------------------- distances
_CHI_CACHE: dict[tuple[str, float], float] = {}


def _default_cosmo():
    from astropy.cosmology import Planck18

    return Planck18


_COSMO_KEYS: dict[int, tuple[Any, str]] = {}


def _cosmo_key(cosmo) -> str:
    """Cache key of a cosmology: its repr (slow for astropy objects), memoised per object."""
    hit = _COSMO_KEYS.get(id(cosmo))
    if hit is None or hit[0] is not cosmo:
        hit = (cosmo, f"{type(cosmo).__name__}:{cosmo!r}")
        _COSMO_KEYS[id(cosmo)] = hit
    return hit[1]


def comoving_distance(z: np.ndarray | float, cosmo=None) -> np.ndarray:
    """Line-of-sight comoving distance [Mpc] (float64 numpy), cached per redshift."""
    cosmo = _default_cosmo() if cosmo is None else cosmo
    key = _cosmo_key(cosmo)
    z = np.asarray(z, dtype=np.float64)
    flat = z.reshape(-1)
    uniq = np.unique(flat)
    missing = [v for v in uniq.tolist() if (key, v) not in _CHI_CACHE]
    if missing:
        vals = np.atleast_1d(cosmo.comoving_distance(np.asarray(missing)).to_value("Mpc"))
        for zz, cc in zip(missing, vals.tolist()):
            _CHI_CACHE[(key, zz)] = float(cc)
    lut = np.array([_CHI_CACHE[(key, v)] for v in uniq.tolist()], dtype=np.float64)
    return lut[np.searchsorted(uniq, flat)].reshape(z.shape)


# ------------------------------------------------------------------------------ planes
@dataclass(frozen=True)
class Plane:
    """A lens plane: redshift, deflectors on it, optional per-system activity.

    ``z``: float, or ``(B,)`` array/tensor for per-system redshifts (pass float64).
    ``deflectors``: callables ``(x, y) -> (ax, ay)`` giving *reduced* deflections
    (convention: see module docstring).
    ``active``: optional ``(B,)`` bool; where False the plane contributes nothing.
    """

    z: float | np.ndarray | Tensor
    deflectors: Sequence[Deflector] = field(default_factory=tuple)
    active: np.ndarray | Tensor | None = None


@dataclass(frozen=True)
class PlaneGeometry:
    """Distance factors of a plane sequence, float64 numpy, each ``(n_planes, B)``.

    ``c_prev``, ``c_dir``: position recursion coefficients (``chi_p/chi_j``,
    ``(chi_j - chi_p)/chi_j``); ``to_physical``: ``chi_c / (chi_c - chi_j)``;
    ``to_source``: ``(chi_s - chi_j)/chi_s * to_physical`` or None when ``z_c = z_s``
    (weight 1 exactly); ``active``: bool.  ``B`` is 1 when nothing is per system.
    """

    c_prev: np.ndarray
    c_dir: np.ndarray
    to_physical: np.ndarray
    to_source: np.ndarray | None
    active: np.ndarray


def _to_np(v, name: str) -> np.ndarray:
    if isinstance(v, Tensor):
        v = v.detach().cpu().numpy()
    arr = np.asarray(v)
    if arr.ndim > 1 or (arr.ndim == 1 and arr.size == 0):
        raise ValueError(f"{name} must be a scalar or a 1-D (B,) array, got shape {arr.shape}")
    return arr


def plane_geometry(
    z_planes: Sequence,
    z_source,
    *,
    active: Sequence | None = None,
    cosmo=None,
    z_convention=None,
    beyond_source: str = "raise",
) -> PlaneGeometry:
    """Distance factors for planes at ``z_planes`` (each scalar or ``(B,)``), in the
    given order, for sources at ``z_source`` (scalar or ``(B,)``).

    Raises ``ValueError`` for non-positive plane redshifts, planes at or behind the
    source (unless ``beyond_source="skip"``, which deactivates them for the
    systems concerned), active planes out of redshift order, or a curved ``cosmo``.
    """
    cosmo = _default_cosmo() if cosmo is None else cosmo
    ok0 = float(getattr(cosmo, "Ok0", 0.0))
    if abs(ok0) > 1e-12:
        raise ValueError(
            f"cosmo must be flat for the comoving multi-plane recursion, got Ok0={ok0}"
        )
    if beyond_source not in ("raise", "skip"):
        raise ValueError(f"beyond_source must be 'raise' or 'skip', got {beyond_source!r}")
    n = len(z_planes)
    act_in = [None] * n if active is None else list(active)
    if len(act_in) != n:
        raise ValueError(f"active has {len(act_in)} entries for {n} planes")
    zs = _to_np(z_source, "z_source").astype(np.float64)
    zc = zs if z_convention is None else _to_np(z_convention, "z_convention").astype(np.float64)
    zp = [_to_np(z, f"planes[{j}].z").astype(np.float64) for j, z in enumerate(z_planes)]
    ac = [
        np.ones((), bool) if a is None else _to_np(a, f"planes[{j}].active").astype(bool)
        for j, a in enumerate(act_in)
    ]
    try:
        shapes = [zs.shape, zc.shape, *[z.shape for z in zp], *[a.shape for a in ac]]
        b = np.broadcast_shapes(*shapes)
    except ValueError:
        raise ValueError(
            f"per-system redshifts/active masks have incompatible shapes {shapes}"
        ) from None
    nb = b[0] if b else 1
    zs = np.broadcast_to(zs, (nb,))
    zc = np.broadcast_to(zc, (nb,))
    if np.any(zs <= 0) or np.any(zc <= 0):
        raise ValueError(f"z_source / z_convention must be > 0, got {zs.min()} / {zc.min()}")
    zp_arr = np.stack([np.broadcast_to(z, (nb,)) for z in zp]) if n else np.zeros((0, nb))
    act = np.stack([np.broadcast_to(a, (nb,)) for a in ac]).copy() if n else np.zeros((0, nb), bool)
    if n and np.any(zp_arr <= 0):
        j = int(np.argwhere(zp_arr <= 0)[0, 0])
        raise ValueError(f"planes[{j}].z must be > 0, got {zp_arr[j].min()}")
    behind = act & ((zp_arr >= zs[None, :]) | (zp_arr >= zc[None, :]))
    if np.any(behind):
        if beyond_source == "raise":
            j, bb = (int(v) for v in np.argwhere(behind)[0])
            raise ValueError(
                f"planes[{j}].z = {zp_arr[j, bb]} is not in front of the source (z_source = "
                f"{zs[bb]}, z_convention = {zc[bb]}) for system {bb}; planes must satisfy "
                "z < z_source (use beyond_source='skip' or active masks to drop them)"
            )
        act &= ~behind
    return _recursion_factors(zp_arr, act, zs, zc, cosmo, z_convention is not None)


def _recursion_factors(zp_arr, act, zs, zc, cosmo, with_source: bool) -> PlaneGeometry:
    """The comoving recursion's factors per plane and system (planes ``(n, B)``, active
    masks, source and convention redshifts ``(B,)``)."""
    n, nb = zp_arr.shape
    chi = comoving_distance(zp_arr, cosmo) if n else zp_arr
    chi_s = comoving_distance(zs, cosmo)
    chi_c = comoving_distance(zc, cosmo)
    c_prev = np.ones((n, nb))
    c_dir = np.zeros((n, nb))
    to_phys = np.zeros((n, nb))
    chi_p = np.zeros(nb)
    z_p = np.zeros(nb)
    for j in range(n):
        a = act[j]
        if np.any(a & (chi[j] < chi_p)):
            bb = int(np.argwhere(a & (chi[j] < chi_p))[0, 0])
            raise ValueError(
                f"planes[{j}].z = {zp_arr[j, bb]} lies in front of the previous active plane "
                f"(z = {z_p[bb]}) for system {bb}; order the planes by redshift for every "
                "system (duplicate per-system-ordered planes with complementary active masks)"
            )
        c_prev[j] = np.where(a, chi_p / chi[j], 1.0)
        c_dir[j] = np.where(a, (chi[j] - chi_p) / chi[j], 0.0)
        to_phys[j] = np.where(a, chi_c / np.where(a, chi_c - chi[j], 1.0), 0.0)
        chi_p = np.where(a, chi[j], chi_p)
        z_p = np.where(a, zp_arr[j], z_p)
    to_source = None
    if with_source:
        to_source = np.where(act, (chi_s[None] - chi) / chi_s[None] * to_phys, 0.0)
    return PlaneGeometry(c_prev, c_dir, to_phys, to_source, act)


def _is_scalar(z) -> bool:
    return (isinstance(z, Tensor) and z.dim() == 0) or np.ndim(z) == 0


def multi_plane_ray_shoot(
    x: Tensor,
    y: Tensor,
    planes: Sequence[Plane],
    z_source,
    *,
    cosmo=None,
    z_convention=None,
    beyond_source: str = "raise",
) -> tuple[Tensor, Tensor]:
    """Multi-plane lens equation: image-plane ``(x, y)`` [arcsec] → source ``(beta_x, beta_y)``.

    Parameters
    ----------
    x, y : ``(B, P)`` (or ``(P,)``, broadcast) angular coordinates [arcsec].
    planes : :class:`Plane` list.  If every plane redshift is a scalar, planes are
        stably sorted by redshift; otherwise their order is used as given and must be
        a redshift order for every system's active planes.
    z_source : scalar or ``(B,)`` source redshift(s).
    cosmo : flat astropy cosmology (default Planck18).
    z_convention : redshift(s) for which the deflector parameters give reduced
        deflections (default: ``z_source``, lenstronomy's ``z_source_convention``).
    beyond_source : ``"raise"`` (default) or ``"skip"`` planes with ``z >= z_source``.

    Every plane is evaluated once, in one front-to-back sweep; distance factors are
    ``(B, 1)`` tensors in ``x``'s dtype and device.
    """
    planes = list(planes)
    bad = [type(p).__name__ for p in planes if not isinstance(p, Plane)]
    if bad:
        j = next(j for j, p in enumerate(planes) if not isinstance(p, Plane))
        raise ValueError(f"planes[{j}] must be a subslope.physics.raytrace.Plane, got {bad[0]}")
    if all(_is_scalar(p.z) for p in planes):
        planes = sorted(planes, key=lambda p: float(p.z))
    geom = plane_geometry(
        [p.z for p in planes],
        z_source,
        active=[p.active for p in planes],
        cosmo=cosmo,
        z_convention=z_convention,
        beyond_source=beyond_source,
    )

    def t(a: np.ndarray) -> Tensor:
        return torch.as_tensor(a, dtype=x.dtype, device=x.device)[:, None]

    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    px, py = x, y  # angular position at the previous active plane
    dirx, diry = x, y  # ray direction (physical angle), starts as theta
    sx = sy = None  # sum of reduced deflections weighted to the source
    n = len(planes)
    for j, plane in enumerate(planes):
        act = geom.active[j]
        if not act.any():
            continue
        if np.all(geom.c_prev[j] == 0.0) and np.all(geom.c_dir[j] == 1.0):
            tx, ty = dirx, diry  # first plane: theta_j = theta exactly
        elif np.all(geom.c_prev[j] == 1.0) and np.all(geom.c_dir[j] == 0.0):
            tx, ty = px, py  # same redshift as previous plane
        else:
            cp, cd = t(geom.c_prev[j]), t(geom.c_dir[j])
            tx, ty = cp * px + cd * dirx, cp * py + cd * diry
        ax, ay = deflection_sum(tx, ty, plane.deflectors)
        if not act.all():
            m = torch.as_tensor(act, device=x.device)[:, None]
            ax, ay = torch.where(m, ax, zero), torch.where(m, ay, zero)
        if geom.to_source is not None:
            ws = t(geom.to_source[j])
            ax_s, ay_s = ws * ax, ws * ay
        else:
            ax_s, ay_s = ax, ay
        sx = ax_s if sx is None else sx + ax_s
        sy = ay_s if sy is None else sy + ay_s
        if j < n - 1:  # direction needed by later planes only
            f = t(geom.to_physical[j])
            dirx, diry = dirx - f * ax, diry - f * ay
        px, py = tx, ty
    if sx is None or sy is None:
        return x + torch.zeros_like(x), y + torch.zeros_like(y)
    return x - sx, y - sy
