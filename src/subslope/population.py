"""Masked, chunked sums of one profile type over a population axis.

A *population* is a set of ``N`` deflectors of the same profile type per system
(subhalos of a lens, halos of one line-of-sight slice).  The number of members
varies from system to system, so a batch of ``B`` systems is stored padded: every
parameter is a tensor of shape ``(B, N)`` and a boolean ``mask`` of shape ``(B, N)``
says which slots are real members (``True``) and which are padding (``False``).

Evaluation broadcasts parameters ``(B, n, 1)`` against coordinates ``(B, 1, P)``
(``docs/design.md``), one chunk of ``n`` members at a time, and sums over the
member axis.  Padded members contribute exactly zero:

1. before evaluation their parameters are replaced by *safe* values (the first
   valid member of the same system, else the first valid member of the batch, else
   ``pad_values``), so that padding such as ``0`` or ``NaN`` cannot create NaN/Inf
   in the forward pass *or* in gradients;
2. after evaluation the padded outputs are selected away with ``torch.where``
   (never multiplied by zero, which would let ``NaN * 0 = NaN`` through).

Memory knob
-----------
The largest intermediate of a profile evaluation has ``B * n * P`` elements.  The
chunk size ``n`` is ``chunk_size`` when given, otherwise
``max(1, max_elements // (B * P))`` (see :func:`choose_chunk_size`).  Profile
functions hold a handful (EPL with its hypergeometric series: ~10-20) of such
intermediates at once, so peak memory is roughly
``k * max_elements * itemsize`` with ``k`` ~ 10-20; the default
``max_elements = 2**22`` gives ~0.3-0.7 GB in float64 and half that in float32.
Raise it on a GPU for speed.  The only Python loop is over chunks.

Ragged storage
--------------
The simulator stores populations as flat arrays plus per-system counts (or
offsets, ``offsets[b]:offsets[b+1]`` holds system ``b``).
:func:`pack_ragged` / :func:`unpack_ragged` convert between that layout (numpy)
and the padded layout; :func:`pack_ragged_params` does it for a dict of
parameters and returns torch tensors.

Negative mass sheet
-------------------
:func:`negative_sheet_convergence` returns, per system, minus the mean over the
image pixels of the summed population convergence (SCIENCE.md §4, §5); the
matching deflection of a uniform sheet centred on the origin is
:func:`sheet_deflector` (``alpha = kappa_sheet * (x, y)``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "DEFAULT_MAX_ELEMENTS",
    "choose_chunk_size",
    "counts_to_offsets",
    "negative_sheet_convergence",
    "pack_ragged",
    "pack_ragged_params",
    "population_deflection",
    "population_sum",
    "safe_params",
    "sheet_deflector",
    "unpack_ragged",
]

#: default bound on ``B * chunk * P`` (elements of one broadcast intermediate)
DEFAULT_MAX_ELEMENTS = 2**22


# --------------------------------------------------------------------------- chunking
def choose_chunk_size(n_systems: int, n_members: int, n_points: int,
                      max_elements: int = DEFAULT_MAX_ELEMENTS) -> int:
    """Number of members evaluated at once so that ``B * chunk * P <= max_elements``.

    Always at least 1 and at most ``n_members`` (or 1 when ``n_members == 0``).
    """
    if max_elements < 1:
        raise ValueError(f"max_elements must be >= 1, got {max_elements}")
    per_member = max(1, int(n_systems) * int(n_points))
    return int(max(1, min(max(int(n_members), 1), max_elements // per_member)))


# ------------------------------------------------------------------------ safe params
def safe_params(params: Mapping[str, Tensor], mask: Tensor,
                pad_values: Mapping[str, float] | None = None) -> dict[str, Tensor]:
    """Replace padded slots of every ``(B, N)`` parameter with safe values.

    The safe value of a system is its first valid member's value; a system with no
    valid member takes the first valid member of the whole batch; when the batch
    has none, ``pad_values[key]`` is used (if given) or the values are left as they
    are (they are masked out of every result anyway).
    """
    pad_values = dict(pad_values or {})
    out: dict[str, Tensor] = {}
    if mask.numel() == 0:
        return dict(params)
    has_any = mask.any(dim=1)  # (B,)
    first_idx = torch.argmax(mask.to(torch.int8), dim=1)  # (B,) first True (0 if none)
    any_valid = bool(has_any.any())
    if any_valid:
        flat_first = int(torch.argmax(mask.reshape(-1).to(torch.int8)))
        gb, gn = divmod(flat_first, mask.shape[1])
    for key, value in params.items():
        if any_valid:
            own = torch.gather(value, 1, first_idx[:, None])  # (B, 1)
            glob = value[gb, gn].reshape(1, 1).expand_as(own)
            fill = torch.where(has_any[:, None], own, glob)
        elif key in pad_values:
            fill = torch.full((value.shape[0], 1), float(pad_values[key]),
                              dtype=value.dtype, device=value.device)
        else:
            out[key] = value
            continue
        out[key] = torch.where(mask, value, fill)
    return out


def _check_population(params: Mapping[str, Tensor], mask: Tensor) -> None:
    if mask.dtype != torch.bool:
        raise ValueError(f"mask must be a bool tensor, got dtype {mask.dtype}")
    if mask.dim() != 2:
        raise ValueError(f"mask must have shape (B, N), got {tuple(mask.shape)}")
    for key, value in params.items():
        if not isinstance(value, Tensor):
            raise ValueError(f"params[{key!r}] must be a torch.Tensor, got {type(value).__name__}")
        if tuple(value.shape) != tuple(mask.shape):
            raise ValueError(
                f"params[{key!r}] has shape {tuple(value.shape)}; it must equal the mask "
                f"shape (B, N) = {tuple(mask.shape)}")


def _as_bp(x: Tensor, name: str) -> Tensor:
    if x.dim() == 1:
        return x[None, :]
    if x.dim() == 2:
        return x
    raise ValueError(f"{name} must have shape (B, P) or (P,), got {tuple(x.shape)}")


# ----------------------------------------------------------------------- population sum
def population_sum(fn: Callable[..., Any], x: Tensor, y: Tensor,
                   params: Mapping[str, Tensor], mask: Tensor, *,
                   chunk_size: int | None = None,
                   max_elements: int = DEFAULT_MAX_ELEMENTS,
                   pad_values: Mapping[str, float] | None = None,
                   **static_kwargs: Any) -> Tensor | tuple[Tensor, ...]:
    """Sum ``fn`` over the members of a padded population.

    Parameters
    ----------
    fn : callable ``fn(x, y, **member_params, **static_kwargs)`` returning a tensor
        or a tuple of tensors, evaluated with ``x, y`` of shape ``(B, 1, P)`` and
        member parameters of shape ``(B, n, 1)``; outputs broadcast to ``(B, n, P)``.
    x, y : ``(B, P)`` or ``(P,)`` angular coordinates [arcsec].
    params : dict of ``(B, N)`` tensors, one per member parameter of ``fn``.
    mask : ``(B, N)`` bool, ``True`` for real members.
    chunk_size : members per evaluation; default from ``max_elements``.
    max_elements : bound on ``B * chunk * P`` when ``chunk_size`` is None.
    pad_values : fallback parameter values for padded slots (see :func:`safe_params`).
    static_kwargs : passed unchanged to ``fn`` (e.g. ``n_terms``).

    Returns
    -------
    Same structure as ``fn``'s output, each of shape ``(B, P)``: the sum over valid
    members.  A system without members gets exact zeros.
    """
    _check_population(params, mask)
    x = _as_bp(x, "x")
    y = _as_bp(y, "y")
    n_sys, n_mem = mask.shape
    n_pts = max(x.shape[-1], y.shape[-1])
    b_out = max(n_sys, x.shape[0], y.shape[0])
    if chunk_size is None:
        chunk_size = choose_chunk_size(b_out, n_mem, n_pts, max_elements)
    elif int(chunk_size) < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    chunk_size = int(chunk_size)

    safe = safe_params(params, mask, pad_values)
    xe, ye = x[:, None, :], y[:, None, :]
    total: list[Tensor] | None = None
    is_tuple = True
    for start in range(0, n_mem, chunk_size):
        m = mask[:, start:start + chunk_size]
        if not bool(m.any()):
            continue
        kw = {k: v[:, start:start + chunk_size, None] for k, v in safe.items()}
        res = fn(xe, ye, **kw, **static_kwargs)
        if isinstance(res, Tensor):
            is_tuple = False
            res = (res,)
        shape = (b_out, m.shape[1], n_pts)
        part = []
        for r in res:
            r = torch.broadcast_to(r, shape)
            zero = torch.zeros((), dtype=r.dtype, device=r.device)
            part.append(torch.where(m[:, :, None], r, zero).sum(dim=1))
        total = part if total is None else [t + p for t, p in zip(total, part)]
    if total is None:
        # no valid member anywhere: evaluate an empty chunk (for the output arity,
        # dtype and shape) and sum it, which gives exact zeros of shape (B, P)
        kw = {k: v[:, :0, None] for k, v in safe.items()}
        res = fn(xe, ye, **kw, **static_kwargs)
        is_tuple = not isinstance(res, Tensor)
        res = res if is_tuple else (res,)
        total = [torch.broadcast_to(r, (b_out, 0, n_pts)).sum(dim=1) for r in res]
    return tuple(total) if is_tuple else total[0]


def population_deflection(deflection_fn: Callable[..., tuple[Tensor, Tensor]],
                          x: Tensor, y: Tensor, params: Mapping[str, Tensor],
                          mask: Tensor, **kwargs: Any) -> tuple[Tensor, Tensor]:
    """Summed deflection ``(ax, ay)``, each ``(B, P)`` [arcsec], of a padded population.

    ``deflection_fn(x, y, **params) -> (ax, ay)`` is any profile deflection;
    keyword arguments are those of :func:`population_sum`.
    """
    ax, ay = population_sum(deflection_fn, x, y, params, mask, **kwargs)
    return ax, ay


# ----------------------------------------------------------------------- negative sheet
def negative_sheet_convergence(kappa_fn: Callable[..., Tensor], x: Tensor, y: Tensor,
                               params: Mapping[str, Tensor], mask: Tensor,
                               **kwargs: Any) -> Tensor:
    """Convergence of the negative mass sheet of a population, shape ``(B, 1)``.

    ``kappa_sheet = - mean over the P image pixels of sum_members kappa_i(x, y)``,
    so that population + sheet has zero mean convergence over the image.  ``x, y``
    are the image pixel coordinates (for a line-of-sight slice: the image grid
    mapped to that slice is the reference's choice; the pixel grid is a good proxy).
    ``kwargs`` go to :func:`population_sum`.
    """
    kappa = population_sum(kappa_fn, x, y, params, mask, **kwargs)
    if not isinstance(kappa, Tensor):
        raise ValueError("kappa_fn must return a single tensor (the convergence)")
    return -kappa.mean(dim=-1, keepdim=True)


def sheet_deflector(kappa_sheet: Tensor) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """Deflector of a uniform sheet centred on the origin: ``alpha = kappa * (x, y)``.

    ``kappa_sheet`` of shape ``(B,)`` or ``(B, 1)`` (or a scalar tensor).
    """
    k = kappa_sheet
    if k.dim() == 1:
        k = k[:, None]

    def deflect(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
        return k * x, k * y

    return deflect


# ------------------------------------------------------------------------ ragged layout
def counts_to_offsets(counts: np.ndarray) -> np.ndarray:
    """``(B,)`` counts → ``(B + 1,)`` offsets (``offsets[0] = 0``)."""
    counts = np.asarray(counts)
    if counts.ndim != 1 or (counts.size and counts.min() < 0):
        raise ValueError(f"counts must be a 1-D array of non-negative integers, got {counts!r}")
    return np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])


def _counts_from(counts: np.ndarray | None, offsets: np.ndarray | None, n_flat: int) -> np.ndarray:
    if (counts is None) == (offsets is None):
        raise ValueError("give exactly one of counts= or offsets=")
    if offsets is not None:
        offsets = np.asarray(offsets, dtype=np.int64)
        if offsets.ndim != 1 or offsets.size < 1 or offsets[0] != 0 or np.any(np.diff(offsets) < 0):
            raise ValueError(f"offsets must be non-decreasing, 1-D and start at 0, got {offsets!r}")
        counts = np.diff(offsets)
    counts = np.asarray(counts, dtype=np.int64)
    if counts.ndim != 1 or (counts.size and counts.min() < 0):
        raise ValueError(f"counts must be 1-D and non-negative, got {counts!r}")
    if counts.sum() != n_flat:
        raise ValueError(f"counts/offsets describe {int(counts.sum())} members but values has {n_flat}")
    return counts


def pack_ragged(values: np.ndarray, *, counts: np.ndarray | None = None,
                offsets: np.ndarray | None = None, n_max: int | None = None,
                fill: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Flat ragged array → padded ``(B, n_max)`` array and bool mask (vectorised).

    ``values`` is the concatenation of all systems' members (``(M,)``, or ``(M, ...)``
    for vector-valued members); ``counts`` ``(B,)`` or ``offsets`` ``(B + 1,)``.
    ``n_max`` defaults to ``max(counts)``; padded slots hold ``fill``.
    """
    values = np.asarray(values)
    counts = _counts_from(counts, offsets, values.shape[0])
    n_sys = counts.size
    width = int(counts.max()) if n_max is None and n_sys else int(n_max or 0)
    if n_sys and width < counts.max():
        raise ValueError(f"n_max={n_max} is smaller than the largest count {int(counts.max())}")
    mask = np.arange(width)[None, :] < counts[:, None]
    padded = np.full((n_sys, width) + values.shape[1:], fill, dtype=values.dtype)
    padded[mask] = values  # row-major order of the mask == concatenation order
    return padded, mask


def unpack_ragged(padded: np.ndarray | Tensor, mask: np.ndarray | Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Padded ``(B, N, ...)`` + mask → flat values ``(M, ...)`` and counts ``(B,)``."""
    if isinstance(padded, Tensor):
        padded = padded.detach().cpu().numpy()
    if isinstance(mask, Tensor):
        mask = mask.detach().cpu().numpy()
    mask = np.asarray(mask, dtype=bool)
    if padded.shape[:2] != mask.shape:
        raise ValueError(f"padded shape {padded.shape} does not start with mask shape {mask.shape}")
    return padded[mask], mask.sum(axis=1).astype(np.int64)


def pack_ragged_params(values: Mapping[str, np.ndarray], *, counts: np.ndarray | None = None,
                       offsets: np.ndarray | None = None, n_max: int | None = None,
                       dtype: torch.dtype = torch.float64,
                       device: torch.device | str | None = None) -> tuple[dict[str, Tensor], Tensor]:
    """Pack a dict of flat per-member arrays into ``(B, N)`` tensors and a bool mask.

    Padded slots hold 0; :func:`population_sum` replaces them with safe values.
    """
    out: dict[str, Tensor] = {}
    mask_np = None
    for key, arr in values.items():
        try:
            padded, mask_np = pack_ragged(arr, counts=counts, offsets=offsets, n_max=n_max)
        except ValueError as exc:
            raise ValueError(f"values[{key!r}]: {exc}") from None
        out[key] = torch.as_tensor(padded, dtype=dtype, device=device)
    if mask_np is None:
        raise ValueError("values must hold at least one parameter array")
    return out, torch.as_tensor(mask_np, device=device)
