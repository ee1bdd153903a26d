"""Images from a stored shard: the renderer's inputs rebuilt from the stored values only
(populations at their stored precision, their lens parameters derived as in the
simulation by :func:`subslope.simulation.subhalos.subhalo_population`), the rerender of
an image (bit-exact with its batch), the smooth models that placed its subhalos, and the images with
their halos removed (null tests)."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np
import torch

from subslope.io import shards as _shards
from subslope.physics.instrument import add_noise
from subslope.simulation.los_halos import LosPopulation
from subslope.simulation.observing import build_instrument
from subslope.simulation.precision import rounded_image
from subslope.simulation.shard import _settings_from_json
from subslope.simulation.sources import catalog_at, pixelated_sources, place_source
from subslope.simulation.subhalos import subhalo_population

__all__ = [
    "stored_inputs",
    "rerender",
    "smooth_models",
    "halo_free_images",
    "subhalo_free_images",
    "sheet_kappas",
    "stored_populations",
    "stored_settings",
]


def stored_settings(attrs) -> Any:
    """The render settings a shard was made with (dtype, batching, every knob), on the
    device it was made on where this machine has it, else on this job's device (CUDA if
    present, else the CPU): a shard made on a GPU re-renders on a CPU node."""
    import torch

    settings = _settings_from_json(attrs["render_settings"])
    stored = str(settings.device or "")
    if stored.startswith("cuda") and not torch.cuda.is_available():
        settings = dataclasses.replace(settings, device=None)
    return settings


def stored_inputs(shard: _shards.Shard, indices, *, cosmos=None, settings=None) -> dict[str, Any]:
    """Renderer inputs of the images ``indices`` of an open shard, from stored values only.

    ``cosmos``: COSMOS folder overriding the shard's ``cosmos_folder`` attribute.
    Returns ``macro``, ``sources`` (PixelatedSources or None), ``subhalos``, ``los``,
    ``psf`` (tensor), ``settings``, ``noise_seed``, ``instrument`` and ``sheet_centre``
    (shards written before the sheet centre was a choice: the origin).
    """
    a = shard.attrs
    settings = settings or stored_settings(a)
    idx = np.atleast_1d(np.arange(len(shard))[indices])
    macro = {k: v[idx] for k, v in shard.params.items() if k != "noise_seed"}
    cfg = a["config"]
    zp = float(cfg["instrument"]["zero_point"])
    src = None
    if shard.sources:
        s = shard.sources
        where = cosmos if cosmos is not None else a["cosmos_folder"]
        catalog = catalog_at(
            tuple(str(f) for f in where) if isinstance(where, (list, tuple)) else str(where)
        )
        stamps, pixs = [], []
        for i in idx:
            z_s = shard.params["z_source"][i]
            sb, pix, _ = place_source(
                catalog,
                cfg["sources"],
                s["ident"][i],
                z_s,
                zp,
                s["mag"][i] if "mag" in s else None,
            )
            if not np.isclose(pix, s["pixel_scale"][i], rtol=1e-12):
                raise _shards.ShardError(
                    f"{shard.path}: COSMOS galaxy {s['ident'][i]} at z = {z_s} "
                    "does not reproduce the stored pixel scale (different catalogue?)"
                )
            stamps.append(sb)
            pixs.append(s["pixel_scale"][i])
        src = pixelated_sources(stamps, pixs, a["source_pad_shape"], settings)
    subs, lpop = stored_populations(shard, idx, macro)
    psf = torch.as_tensor(shard.psf, dtype=settings.dtype, device=settings.device)
    inst = build_instrument(cfg)
    return {
        "macro": macro,
        "sources": src,
        "subhalos": subs,
        "los": lpop,
        "psf": psf,
        "settings": settings,
        "noise_seed": shard.params["noise_seed"][idx],
        "instrument": inst,
        "sheet_centre": {
            "subhalos": a.get("sheet_centre_subhalos", "origin"),
            "los": a.get("sheet_centre_los", "origin"),
        },
    }


def stored_populations(shard: _shards.Shard, idx: np.ndarray, macro):
    """``(subhalos, los)`` of the images ``idx`` of an open shard, rebuilt from their
    stored members (``macro``: the images' stored parameters); None for a population the
    scene does not have."""
    a = shard.attrs
    subs = lpop = None
    if a["subhalo_profile"] != "none":
        drawn = shard.ragged("subhalos", idx)
        counts = drawn.pop("counts")
        subs = subhalo_population(a["subhalo_profile"], counts, drawn, macro)
    if a["los_profile"] != "none":
        stored_los = shard.ragged("los", idx)
        lpop = LosPopulation(
            profile=a["los_profile"],
            **{k: v if k == "counts" else v.astype(np.float64) for k, v in stored_los.items()},
        )
    return subs, lpop


def rerender(
    shard_path: str | os.PathLike[str],
    i: int,
    *,
    noise: bool = True,
    cosmos=None,
    alone: bool = False,
) -> np.ndarray:
    """Image ``i`` of a shard re-rendered from its stored parameters (nothing re-sampled).

    The shard job renders its images in batches of the stored ``batch_images``; by
    default the image is rendered with the rest of its batch, and on the same device and
    dtype the result equals the stored image bit for bit. ``alone=True`` renders image
    ``i`` by itself (``batch_images`` times cheaper), noise-free only: it agrees with
    the batch's noise-free image to float rounding, i.e. to within one unit in the last
    stored place (16-bit mantissa) per pixel (``docs/simulation.md``). Noise is not
    offered alone: the Poisson sampler's rejection loop consumes a data-dependent number
    of random numbers, so one draw moved by rounding moves every later draw of the image.
    ``noise=False`` gives the noise-free image at the stored precision.
    """
    if alone and noise:
        raise ValueError("rerender(alone=True) gives the noise-free image only: pass noise=False")
    from subslope.render.pipeline import render

    with _shards.open_shard(shard_path) as shard:
        n = len(shard)
        if not 0 <= int(i) < n:
            raise IndexError(f"image index {i} out of range for {shard_path} with {n} images")
        settings = stored_settings(shard.attrs)
        bs = 1 if alone else settings.batch_images
        lo = int(i) // bs * bs
        inp = stored_inputs(shard, np.arange(lo, min(lo + bs, n)), cosmos=cosmos, settings=settings)
    clean = render(
        inp["macro"],
        inp["psf"],
        inp["settings"],
        sources=inp["sources"],
        subhalos=inp["subhalos"],
        los=inp["los"],
        sheet_centre=inp["sheet_centre"],
    )[int(i) - lo]
    img = (
        add_noise(clean, int(inp["noise_seed"][int(i) - lo]), instrument=inp["instrument"])
        if noise
        else clean
    )
    return rounded_image(img.detach().cpu().numpy())


def smooth_models(shard_path: str | os.PathLike[str], indices, *, cosmos=None) -> np.ndarray:
    """Noise-free smooth models (main lens + shear + multipoles + source, no lens light or
    substructure) of images ``indices``, from stored parameters: (k, H, W) float64."""
    from subslope.render.pipeline import render_smooth

    with _shards.open_shard(shard_path) as shard:
        inp = stored_inputs(shard, indices, cosmos=cosmos)
    out = render_smooth(inp["macro"], inp["psf"], inp["settings"], sources=inp["sources"])
    return out.detach().cpu().numpy().astype(np.float64)


def halo_free_images(
    shard_path: str | os.PathLike[str],
    indices,
    *,
    keep_sheets: bool,
    cosmos=None,
    chunk: int = 64,
) -> np.ndarray:
    """Images ``indices`` of a shard re-rendered from their stored parameters with every
    subhalo and line-of-sight halo removed: their negative sheets kept
    (``keep_sheets``, the halos' own deflections dropped) or removed too. Lens, source,
    lens light, sky and the stored noise seeds are the shard's; rounded to the stored
    precision. ``(k, H, W)`` float32, e⁻/s per pixel."""
    return _rerendered(
        shard_path,
        indices,
        lambda inp: {
            "subhalos": inp["subhalos"] if keep_sheets else None,
            "los": inp["los"] if keep_sheets else None,
            "members": False,
        },
        cosmos=cosmos,
        chunk=chunk,
    )


def subhalo_free_images(
    shard_path: str | os.PathLike[str], indices, *, cosmos=None, chunk: int = 64
) -> np.ndarray:
    """Images ``indices`` of a shard re-rendered from their stored parameters without
    their subhalos (and the subhalos' negative sheet); the line-of-sight halos, lens,
    source, lens light, sky and noise seeds as stored. Rounded to the stored precision,
    ``(k, H, W)`` float32, e⁻/s per pixel. Beside the shard's own images it measures
    what the subhalos add to an image (:mod:`subslope.stages.null_tests.visibility`)."""
    return _rerendered(
        shard_path,
        indices,
        lambda inp: {"subhalos": None, "los": inp["los"], "members": True},
        cosmos=cosmos,
        chunk=chunk,
    )


def _rerendered(shard_path, indices, halos, *, cosmos, chunk: int) -> np.ndarray:
    """Noisy images ``indices`` re-rendered ``chunk`` at a time with the halo arguments
    ``halos(inputs)`` of :func:`subslope.render.pipeline.render` (subhalos, los, members)
    and the stored noise seeds, rounded to the stored precision."""
    from subslope.render.pipeline import render

    idx = np.atleast_1d(np.asarray(indices, dtype=np.int64))
    out = []
    with _shards.open_shard(shard_path) as shard:
        shape = tuple(shard.images.shape[1:])
        for s in range(0, idx.size, chunk):
            inp = stored_inputs(shard, idx[s : s + chunk], cosmos=cosmos)
            clean = render(
                inp["macro"],
                inp["psf"],
                inp["settings"],
                sources=inp["sources"],
                sheet_centre=inp["sheet_centre"],
                **halos(inp),
            )
            for j in range(clean.shape[0]):
                img = add_noise(clean[j], int(inp["noise_seed"][j]), instrument=inp["instrument"])
                out.append(rounded_image(img.detach().cpu().numpy()))
    return np.stack(out) if out else np.zeros((0, *shape), np.float32)


def sheet_kappas(
    shard_path: str | os.PathLike[str],
    indices,
    *,
    stride: int = 4,
    member_chunk: int = 256,
) -> dict[str, np.ndarray]:
    """The κ of the negative sheets of images ``indices``: ``{"subhalos": (k,), "los":
    (k,)}``, minus the mean over the image of the members' summed convergence, from their
    stored parameters and the analytic convergence of their profile, in float64 (0 for an
    image without such halos). ``los`` sums the sheets of all line-of-sight planes, each
    taken on the image-plane grid (the rays' displacement on the way is left out, so it
    is the sheets' amplitude, not their lensing weight). The mean is over every
    ``stride``-th pixel centre in each direction, the subgrid centred (``stride=1``:
    every pixel, as the renderer does for the subhalos; 4 is within 10% of it and costs
    1/16). A diagnostic of the halo-free null test: a sheet is a function of its
    members, so of their γ."""
    from subslope.physics.grid import pixel_grid

    idx = np.atleast_1d(np.asarray(indices, dtype=np.int64))
    with _shards.open_shard(shard_path) as shard:
        npix = int(shard.images.shape[-1])
        pixel = float(shard.attrs["config"]["instrument"]["pixel_scale"])
        idx = np.atleast_1d(np.arange(len(shard))[idx])
        macro = {k: v[idx] for k, v in shard.params.items() if k != "noise_seed"}
        subs, lpop = stored_populations(shard, idx, macro)
    pops = {k: v for k, v in (("subhalos", subs), ("los", lpop)) if v is not None}
    x, y = pixel_grid(npix, pixel, dtype=torch.float64)
    start = ((npix - 1) % stride) // 2  # the subgrid as centred as the stride allows
    x = x[start::stride, start::stride].reshape(1, -1)
    y = y[start::stride, start::stride].reshape(1, -1)
    out = {"subhalos": np.zeros(idx.size), "los": np.zeros(idx.size)}
    for name, pop in pops.items():
        kappa = _CONVERGENCE[pop.profile]
        params = {
            k: np.asarray(getattr(pop, k), dtype=np.float64) for k in _profile_keys(pop.profile)
        }
        first = np.concatenate([[0], np.cumsum(pop.counts)])
        for j in range(idx.size):
            total = 0.0
            for s in range(int(first[j]), int(first[j + 1]), member_chunk):
                e = min(s + member_chunk, int(first[j + 1]))
                p = {k: torch.as_tensor(v[s:e])[:, None] for k, v in params.items()}
                total += float(kappa(x, y, p).sum())
            out[name][j] = -total / x.shape[-1]
    return out


def _profile_keys(profile: str):
    from subslope.render.populations import PROFILE_KEYS

    return PROFILE_KEYS[profile]


def _epl_kappa(x, y, p):
    from subslope.physics.profiles.epl import epl_convergence

    return epl_convergence(x, y, p["amp"], p["gamma"], p["e1"], p["e2"], p["x"], p["y"])


def _nfw_kappa(x, y, p):
    from subslope.physics.profiles.nfw import nfw_convergence

    return nfw_convergence(x, y, p["r_s"], p["alpha_rs"], p["x"], p["y"])


def _tnfw_kappa(x, y, p):
    from subslope.physics.profiles.tnfw import tnfw_convergence

    return tnfw_convergence(x, y, p["r_s"], p["alpha_rs"], p["r_t"], p["x"], p["y"])


#: The analytic convergence of one member per profile, ``(x, y, params) -> κ``.
_CONVERGENCE = {"epl": _epl_kappa, "nfw": _nfw_kappa, "tnfw": _tnfw_kappa}
