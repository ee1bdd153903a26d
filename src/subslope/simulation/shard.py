"""The forward simulator: one scene's parameters → noisy images → an HDF5 shard.

:func:`simulate_shard` produces one shard file (layout in :mod:`subslope.io.shards`):

1. **Seeds.** A numpy ``SeedSequence(entropy=config seed, spawn_key=(scene id, shard))``
   per shard (scene id: first 8 bytes of the SHA-256 of the scene name), spawned into
   five independent streams: macro, sources, subhalos, LoS, noise. Subhalos and LoS get
   one child stream *per image* and the noise one torch seed per image (stored), so the
   draws do not depend on the batch size. The CDM scenes (NFW or tNFW subhalos) key
   their seed by :data:`CDM_DRAWS` instead of their own name, at every concentration
   multiplier: shard k of the NFW and the tNFW scene at every a holds the same lenses,
   sources, subhalo masses and positions, LoS halos and noise seeds, the concentrations
   scaled by a and, for tNFW, the subhalos truncated (common random numbers: figure 4
   compares multipliers and profiles on the same sets).
2. **Macro parameters** of all images (:func:`subslope.simulation.macro.sample_macro`).
3. **Sources**: a COSMOS galaxy of the scene's split per image (uniform), moved to the
   image's z_source (:func:`subslope.io.cosmos.place_at_redshift`), optionally
   renormalised to a drawn magnitude, rotated by the macro ``src_rotation``; or the
   parametric Sérsic source of the macro draw.
4. **Per batch** of ``simulation.render.batch_images`` images: the smooth model
   (:func:`subslope.render.pipeline.render_smooth`) when subhalos go on the arc; subhalos
   (:func:`subslope.simulation.subhalos.sample_subhalos`); LoS halos
   (:func:`subslope.simulation.los_halos.sample_los_batch` +
   :func:`subslope.simulation.los_halos.los_profiles`), both at their stored precision
   (:mod:`subslope.simulation.precision`); the noise-free image
   (:func:`subslope.render.pipeline.render`); noise
   (:func:`subslope.physics.instrument.add_noise` with the image's seed); the pixels
   rounded to their stored precision.

:func:`subslope.simulation.rerender.rerender` rebuilds image ``i`` of a shard from its
*stored* parameters (nothing is re-sampled): bit for bit with its batch on the same
device and dtype, to the stored precision alone (``docs/simulation.md``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from subslope import config as _config
from subslope._version import __version__
from subslope.devices import pick_device
from subslope.io import shards as _shards
from subslope.physics.instrument import Instrument, add_noise
from subslope.simulation import macro as _macro
from subslope.simulation.los_halos import LosConfig, LosPopulation, los_profiles, sample_los_batch
from subslope.simulation.observing import build_instrument, build_psf, fit_input_light_of
from subslope.simulation.precision import (
    LOS_DTYPE,
    SUBHALO_DTYPES,
    rounded_image,
    rounded_los,
    stored,
)
from subslope.simulation.resolve import (
    resolved_scene,
    same_multiplier,
    scene_multipliers,
    simulation_sections,
)
from subslope.simulation.sources import (
    cosmos_folders,
    draw_sources,
    landing_stamps,
    pixelated_sources,
)
from subslope.simulation.subhalos import ON_IMAGE, SubhaloPopulation, sample_subhalos

__all__ = [
    "STREAMS",
    "scene_id",
    "shard_seed_sequence",
    "CDM_DRAWS",
    "draws_name",
    "build_psf",
    "build_instrument",
    "render_settings",
    "simulate_images",
    "simulate_shard",
    "sheet_centres",
]

log = logging.getLogger(__name__)

#: The name the CDM scenes' shards key their seed by (module docstring, step 1).
CDM_DRAWS = "cdm"

#: Independent random streams of a shard, in spawn order.
STREAMS = ("macro", "sources", "subhalos", "los", "noise")


# ------------------------------------------------------------------------- naming, seeds
def draws_name(config: Mapping[str, Any], scene: str, multiplier: float | None) -> str:
    """The name a shard of ``scene`` keys its seed by: :data:`CDM_DRAWS` for the CDM
    scenes (a multiplier) and the scenes with ``common_draws: true``, else its own."""
    if multiplier is not None or resolved_scene(config, scene)[0].common_draws:
        return CDM_DRAWS
    return scene


def scene_id(name: str) -> int:
    """Stable 64-bit integer of a scene name (first 8 bytes of its SHA-256)."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "little")


def shard_seed_sequence(
    seed: int, scene: str, shard: int, extra: int | None = None
) -> np.random.SeedSequence:
    """The SeedSequence of one shard: entropy = global seed, spawn key = (scene id,
    shard[, extra]); shards use (scene id, shard), the same for every multiplier of a CDM
    scene."""
    key = (scene_id(scene), int(shard)) + (() if extra is None else (int(extra),))
    return np.random.SeedSequence(entropy=int(seed), spawn_key=key)


# ------------------------------------------------------------------------- set-up


def render_settings(config: Mapping[str, Any]):
    """:class:`subslope.render.settings.RenderSettings` of a validated config, on the
    device this job renders on (``simulation.render.device`` resolved now)."""
    from subslope.render.settings import RenderSettings

    r = config["simulation"]["render"]
    device = str(pick_device(r["device"], key="simulation.render.device"))
    return RenderSettings.from_config(r, config["instrument"], device=device)


def _settings_to_json(settings) -> dict[str, Any]:
    out = {}
    for f in dataclasses.fields(settings):
        v = getattr(settings, f.name)
        if isinstance(v, torch.dtype):
            v = str(v).removeprefix("torch.")
        elif isinstance(v, torch.device):
            v = str(v)
        out[f.name] = v
    return out


def _settings_from_json(d: Mapping[str, Any], device: str | None = None):
    from subslope.render.settings import RenderSettings

    names = {f.name for f in dataclasses.fields(RenderSettings)}
    kw = {k: v for k, v in d.items() if k in names}
    kw["dtype"] = getattr(torch, d["dtype"])
    dev = device if device is not None else d.get("device")
    kw["device"] = None if dev in (None, "None") else str(dev)
    return RenderSettings(**kw)


def _concat_subhalos(pops: Sequence[SubhaloPopulation]) -> SubhaloPopulation:
    first = pops[0]
    kw = {"profile": first.profile}
    for f in dataclasses.fields(SubhaloPopulation):
        if f.name == "profile":
            continue
        vals = [getattr(p, f.name) for p in pops]
        kw[f.name] = None if vals[0] is None else np.concatenate(vals)
    return SubhaloPopulation(**kw)


def _concat_los(pops: Sequence[LosPopulation]) -> LosPopulation:
    kw = {"profile": pops[0].profile}
    for f in dataclasses.fields(LosPopulation):
        if f.name == "profile":
            continue
        vals = [getattr(p, f.name) for p in pops]
        kw[f.name] = None if vals[0] is None else np.concatenate(vals)
    return LosPopulation(**kw)


def _pop_arrays(pop) -> dict[str, np.ndarray]:
    return {
        f.name: getattr(pop, f.name)
        for f in dataclasses.fields(pop)
        if f.name != "profile" and getattr(pop, f.name) is not None
    }


# ------------------------------------------------------------------------- simulation
@dataclasses.dataclass
class _Draws:
    """The per-image random streams of a shard and what the populations need."""

    sub_streams: list
    los_streams: list
    los_config: LosConfig
    npix: int
    pixel_scale: float


def _draw_populations(
    sc, macro: Mapping[str, np.ndarray], idx: range, smooth: np.ndarray | None, draws: _Draws
) -> tuple[SubhaloPopulation | None, LosPopulation | None]:
    """Subhalos (on the arc of the smooth models ``smooth`` when the scene places them
    there) and line-of-sight halos of images ``idx``, each from its own stream."""
    comp = sc.components
    subs = lpop = None
    m_b = {k: v[idx.start : idx.stop] for k, v in macro.items()}
    if comp.subhalos:
        subs = sample_subhalos(
            sc,
            m_b,
            [np.random.default_rng(draws.sub_streams[i]) for i in idx],
            smooth,
            npix=draws.npix,
            pixel_scale=draws.pixel_scale,
        )
    if comp.los:
        rngs = [np.random.default_rng(draws.los_streams[i]) for i in idx]
        batch = sample_los_batch(
            m_b["z_lens"],
            m_b["z_source"],
            m_b["theta_e"],
            m_b["gamma_ml"],
            m_b["delta_los"],
            rngs,
            draws.los_config,
        )
        lpop = rounded_los(los_profiles(batch, sc, m_b, rngs))
    return subs, lpop


@dataclasses.dataclass
class _Job:
    """The state of one in-memory simulation of ``n`` images of a scene."""

    sc: Any
    macro: dict[str, np.ndarray]
    settings: Any
    psf: torch.Tensor
    inst: Instrument
    sources: dict[str, np.ndarray]
    stamps: list[np.ndarray]
    pad_shape: tuple[int, int] | None
    draws: _Draws
    noise_seed: np.ndarray | None
    images: np.ndarray
    timing: dict[str, float]
    sub_pops: list = dataclasses.field(default_factory=list)
    los_pops: list = dataclasses.field(default_factory=list)


def _simulate_batch(job: _Job, sl: slice) -> None:
    """Images ``sl``: smooth models for the arc placement, populations, render, noise."""
    from subslope.render.pipeline import render, render_smooth

    sc, settings, timing = job.sc, job.settings, job.timing
    idx = range(sl.start, sl.stop)
    m_b = {k: v[sl] for k, v in job.macro.items()}
    src_b = None
    if job.stamps:
        src_b = pixelated_sources(
            job.stamps[sl], job.sources["pixel_scale"][sl], job.pad_shape, settings
        )
    t = time.perf_counter()
    smooth = None
    placement = sc.subhalos.placement
    if sc.components.subhalos and placement in ON_IMAGE and np.any(m_b["n_sub"] > 0):
        on = src_b
        if placement == "landing":
            on = pixelated_sources(
                landing_stamps(job.stamps[sl]),
                job.sources["pixel_scale"][sl],
                job.pad_shape,
                settings,
            )
        smooth = render_smooth(m_b, job.psf, settings, sources=on).detach().cpu().numpy()
    timing["smooth"] += time.perf_counter() - t
    t = time.perf_counter()
    subs, lpop = _draw_populations(sc, job.macro, idx, smooth, job.draws)
    job.sub_pops += [subs] if subs is not None else []
    job.los_pops += [lpop] if lpop is not None else []
    timing["sampling"] += time.perf_counter() - t
    t = time.perf_counter()
    clean = render(
        m_b,
        job.psf,
        settings,
        sources=src_b,
        subhalos=subs,
        los=lpop,
        sheet_centre=sheet_centres(sc),
    )
    timing["render"] += time.perf_counter() - t
    t = time.perf_counter()
    _observe(job.images, clean, idx, job.noise_seed, job.inst)
    timing["noise"] += time.perf_counter() - t


def simulate_images(
    config: Mapping[str, Any],
    scene: str,
    n: int,
    seed_sequence: np.random.SeedSequence,
    *,
    multiplier: float | None = None,
    progress: bool = False,
    noise: bool = True,
) -> dict[str, Any]:
    """Simulate ``n`` images of ``scene`` in memory (the body of :func:`simulate_shard`).

    Returns a dict with ``images`` (n, H, W) float32 numpy, ``params`` (per-image macro
    parameters + ``noise_seed``), ``sources``, ``subhalos``, ``los`` (flat arrays +
    ``counts``), ``psf``, ``settings`` (RenderSettings), ``timings`` (s) and profiles.
    """
    config = _config.validate(config)
    sc, _ = resolved_scene(config, scene)
    streams = dict(zip(STREAMS, seed_sequence.spawn(len(STREAMS))))
    t0 = time.perf_counter()
    macro = _macro.sample_macro(
        sc, n, np.random.default_rng(streams["macro"]), multiplier=multiplier
    )
    settings = render_settings(config)
    psf64 = build_psf(config)
    psf = torch.as_tensor(psf64, dtype=settings.dtype, device=settings.device)
    inst = build_instrument(config)
    zero_point = float(config["instrument"]["zero_point"])
    src_rng = np.random.default_rng(streams["sources"])
    sources, stamps, pad_shape = draw_sources(config, sc, macro, src_rng, zero_point)
    timing = dict.fromkeys(("setup", "smooth", "sampling", "render", "noise"), 0.0)
    timing["setup"] = time.perf_counter() - t0
    inst_cfg = config["instrument"]
    los_config = LosConfig(m_min=sc.los.m_min, m_max=sc.los.m_max)
    sub_streams, los_streams = streams["subhalos"].spawn(n), streams["los"].spawn(n)
    draws = _Draws(
        sub_streams, los_streams, los_config, int(inst_cfg["npix"]), float(inst_cfg["pixel_scale"])
    )
    noise_seed = streams["noise"].generate_state(n, dtype=np.uint64)
    images = np.empty((n, draws.npix, draws.npix), dtype=np.float32)
    job = _Job(
        sc,
        macro,
        settings,
        psf,
        inst,
        sources,
        stamps,
        pad_shape,
        draws,
        noise_seed if noise else None,
        images,
        timing,
    )
    _run_batches(job, n, settings.batch_images, scene, progress)
    params = dict(macro)
    params["noise_seed"] = noise_seed
    comp = sc.components
    empty = {"counts": np.zeros(n, dtype=np.int64)}
    timing["total"] = time.perf_counter() - t0
    return {
        "images": images,
        "params": params,
        "sources": sources,
        "subhalos": (
            stored(_pop_arrays(_concat_subhalos(job.sub_pops)), SUBHALO_DTYPES)
            if comp.subhalos
            else empty
        ),
        "los": stored(_pop_arrays(_concat_los(job.los_pops)), LOS_DTYPE) if comp.los else empty,
        "psf": psf64,
        "settings": settings,
        "timings": timing,
        "pad_shape": pad_shape,
        "subhalo_profile": sc.subhalos.profile if comp.subhalos else "none",
        "los_profile": sc.los.profile if comp.los else "none",
        "sheet_centre": sheet_centres(sc),
    }


def _run_batches(job: _Job, n: int, bs: int, scene: str, progress: bool) -> None:
    bar = _progress_bar(n, scene) if progress else None
    for start in range(0, n, bs):
        _simulate_batch(job, slice(start, min(start + bs, n)))
        if bar is not None:
            bar.update(min(start + bs, n) - start)
    if bar is not None:
        bar.close()


def sheet_centres(sc) -> dict[str, str]:
    """The renderer's ``sheet_centre`` of a scene: ``{"subhalos": ..., "los": ...}``."""
    return {"subhalos": sc.subhalos.sheet_centre, "los": sc.los.sheet_centre}


def _observe(images: np.ndarray, clean, idx: range, noise_seed: np.ndarray | None, inst) -> None:
    """Images ``idx`` with their detector noise (each from its own seed; none when
    ``noise_seed`` is None), as float32 at the stored precision
    (:func:`subslope.simulation.precision.rounded_image`) into ``images``."""
    for j, i in enumerate(idx):
        img = (
            add_noise(clean[j], int(noise_seed[i]), instrument=inst)
            if noise_seed is not None
            else clean[j]
        )
        images[i] = rounded_image(img.detach().cpu().numpy())


def _progress_bar(n: int, scene: str):
    from tqdm import tqdm

    return tqdm(total=n, desc=f"{scene} images", unit="img")


def simulate_shard(
    config: Mapping[str, Any],
    scene: str,
    shard: int,
    out_path: str | os.PathLike[str],
    *,
    multiplier: float | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> Path:
    """Simulate shard number ``shard`` of ``scene`` into ``out_path`` (see module doc).

    ``multiplier``: concentration multiplier of a CDM scene (one of
    :func:`scene_multipliers`). Refuses to overwrite an existing file unless
    ``overwrite``. Returns the path.
    """
    config = _config.validate(config)
    out_path = Path(out_path)
    if out_path.exists() and not overwrite:
        raise FileExistsError(f"shard {out_path} already exists; delete it or pass overwrite=True")
    n, spec, multiplier = _shard_request(config, scene, shard, multiplier)
    ss = shard_seed_sequence(config["seed"], draws_name(config, scene, multiplier), shard)
    label = "" if multiplier is None else f" (a = {multiplier:g})"
    log.info("simulating %s shard %d%s: %d images -> %s", scene, shard, label, n, out_path)
    out = simulate_images(config, scene, n, ss, multiplier=multiplier, progress=progress)
    sections = simulation_sections(config, scene)
    attrs = {
        "scene": scene,
        "scene_spec": spec,
        "config": sections,
        "config_hash": _shards.config_hash(sections),
        "seed_entropy": str(ss.entropy),
        "seed_spawn_key": list(ss.spawn_key),
        "package_version": __version__,
        "render_settings": _settings_to_json(out["settings"]),
        "subhalo_profile": out["subhalo_profile"],
        "los_profile": out["los_profile"],
        "sheet_centre_subhalos": out["sheet_centre"]["subhalos"],
        "sheet_centre_los": out["sheet_centre"]["los"],
        "shard_index": int(shard),
        "multiplier": None if multiplier is None else float(multiplier),
        "cosmos_folder": [str(f) for f in cosmos_folders(config)] if out["sources"] else "",
        "source_pad_shape": list(out["pad_shape"]) if out["pad_shape"] else [],
    }
    tm = out["timings"]
    light = None
    if _config.light_fit_enabled(config):
        t = time.perf_counter()
        light = fit_input_light_of(config, out["images"], out["params"]["theta_e"], out["psf"])
        tm["light_fit"] = time.perf_counter() - t
    t = time.perf_counter()
    arrays = {k: out[k] for k in ("images", "params", "psf", "subhalos", "los")}
    path = _shards.write_shard(
        out_path,
        **arrays,
        sources=out["sources"] or None,
        light_fit=light,
        attrs=attrs,
        overwrite=overwrite,
    )
    tm["write"] = time.perf_counter() - t
    log.info(
        "timings (s): %s; %.3f s per image; %d subhalos, %d LoS halos; file %.1f kB",
        {k: round(v, 3) for k, v in tm.items()},
        tm["total"] / max(n, 1),
        int(out["subhalos"]["counts"].sum()),
        int(out["los"]["counts"].sum()),
        path.stat().st_size / 1e3,
    )
    return path


def _shard_request(config: Mapping[str, Any], scene: str, shard: int, multiplier: float | None):
    """Check a shard request against the config: ``(images in the shard, scene spec,
    multiplier as listed or None)``."""
    counts = config["simulation"]["scenes"].get(scene)
    if counts is None:
        raise ValueError(
            f"scene {scene!r} has no entry in simulation.scenes (known: "
            f"{sorted(config['simulation']['scenes'])})"
        )
    sc, spec = resolved_scene(config, scene)
    if not 0 <= int(shard) < int(counts["n_shards"]):
        raise ValueError(
            f"shard = {shard} must be in [0, {counts['n_shards']}) "
            f"(simulation.scenes.{scene}.n_shards)"
        )
    mults = scene_multipliers(config, sc)
    if mults is None:
        if multiplier is not None:
            raise ValueError(f"scene {scene!r} has no NFW/tNFW component: multiplier must be None")
        return int(counts["images_per_shard"]), spec, None
    if multiplier is None:
        raise ValueError(f"scene {scene!r} is a CDM scene: pass multiplier = one of {list(mults)}")
    matches = [k for k, a in enumerate(mults) if same_multiplier(a, multiplier)]
    if not matches:
        raise ValueError(
            f"multiplier = {multiplier!r} is not among {list(mults)} of scene {scene!r}"
        )
    return int(counts["images_per_shard"]), spec, mults[matches[0]]
