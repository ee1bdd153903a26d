"""The per-image (macro) parameters of a scene.

:func:`sample_macro` draws every per-image parameter as float64 numpy arrays (integers
for ``n_sub`` and ``set_index``). All parameters are drawn in a fixed order whether or
not their component is on, then the parameters of switched-off components are dropped
from the result; so switching a component off never changes the other draws.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from subslope.simulation.scenes import MULTI_SERSIC_KEYS, LensLightSpec, Scene, SourceSpec

__all__ = ["sample_macro"]

#: (output key, component or None for always-on, attribute path) in drawing order.
_MACRO: tuple[tuple[str, str | None, str], ...] = (
    ("z_lens", None, "redshifts.z_lens"),
    ("z_source", None, "redshifts.z_source"),
    ("src_x", None, "source.x"),
    ("src_y", None, "source.y"),
    ("src_rotation", None, "source.rotation"),
    ("src_mag", "sersic", "source.mag"),
    ("src_r", "sersic", "source.r_sersic"),
    ("src_n", "sersic", "source.n_sersic"),
    ("src_e1", "sersic", "source.e1"),
    ("src_e2", "sersic", "source.e2"),
    ("lens_x", None, "main_lens.x"),
    ("lens_y", None, "main_lens.y"),
    ("theta_e", None, "main_lens.theta_e"),
    ("lens_e1", None, "main_lens.e1"),
    ("lens_e2", None, "main_lens.e2"),
    ("gamma_ml", None, "main_lens.gamma"),
    ("a3", "multipoles", "multipoles.a3"),
    ("phi3", "multipoles", "multipoles.phi3"),
    ("a4", "multipoles", "multipoles.a4"),
    ("phi4", "multipoles", "multipoles.phi4"),
    ("shear_g1", "shear", "shear.g1"),
    ("shear_g2", "shear", "shear.g2"),
    ("light_mag", "lens_light", "lens_light.mag"),
    ("light_r", "lens_light", "lens_light.r_sersic"),
    ("light_n", "lens_light", "lens_light.n_sersic"),
    ("light_e1", "lens_light", "lens_light.e1"),
    ("light_e2", "lens_light", "lens_light.e2"),
    ("n_sub", "subhalos", "subhalos.count"),
    ("delta_los", "los", "los.delta_los"),
)


def _attr(obj: Any, path: str) -> Any:
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def sample_macro(
    scene: Scene, n: int, rng: np.random.Generator, *, multiplier: float | None = None
) -> dict[str, np.ndarray]:
    """Draw the per-image parameters of ``n`` images of ``scene``.

    Parameters
    ----------
    scene : Scene
    n : int
        Number of images; a multiple of ``scene.images_per_set``.
    rng : numpy.random.Generator
        The only source of randomness.
    multiplier : float, optional
        Concentration multiplier ``a`` for CDM scenes (``scene.uses_concentration``);
        may be omitted when the scene lists exactly one multiplier.

    Returns
    -------
    dict of str -> ndarray, each of shape ``(n,)``
        float64 arrays keyed as in ``_MACRO`` (angles in arcsec, angles φ in rad,
        masses not included), plus ``n_sub`` (int64, subhalos on), ``gamma_sub``
        (label γ, when ``scene.has_label``; shared by the images of a set),
        ``c_multiplier`` (CDM scenes), ``sky_level`` (e⁻/s per pixel, ``components.sky``)
        and ``set_index`` (int64). Lens light is centred on ``lens_x, lens_y``; with a
        joint lens-light prior its five keys come from that draw. Keys of switched-off
        components are absent.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n = {n!r} must be a positive integer number of images")
    k = scene.images_per_set
    if n % k:
        raise ValueError(
            f"n = {n} must be a multiple of images_per_set = {k} of scene {scene.name!r}"
        )
    n_sets = n // k
    comp = scene.components
    on = {
        None: True,
        "sersic": scene.source.kind == "sersic",
        **{c: getattr(comp, c) for c in ("multipoles", "shear", "lens_light", "subhalos", "los")},
    }
    out: dict[str, np.ndarray] = {}
    drawn: dict[str, np.ndarray] = {}
    for name, component, path in _MACRO:
        draw = _attr(scene, path).sample(rng, n)  # always drawn: keeps the stream aligned
        drawn[name] = draw
        if on[component]:
            out[name] = draw
    gamma_sets = scene.subhalos.gamma.sample(rng, n_sets)
    if scene.subhalos.fixed_gamma is not None:  # drawn first: the stream stays aligned
        gamma_sets = np.full(n_sets, scene.subhalos.fixed_gamma)
    if "n_sub" in out:
        out["n_sub"] = out["n_sub"].astype(np.int64)
    if scene.has_label:
        out["gamma_sub"] = np.repeat(gamma_sets, k)
    if scene.uses_concentration:
        mults = scene.concentration.multipliers
        if multiplier is None:
            if len(mults) != 1:
                raise ValueError(
                    f"scene {scene.name!r} lists several concentration multipliers {list(mults)}; "
                    "pass multiplier=<one of them>"
                )
            multiplier = mults[0]
        if not (
            isinstance(multiplier, (int, float)) and math.isfinite(multiplier) and multiplier > 0
        ):
            raise ValueError(f"multiplier = {multiplier!r} must be a finite number > 0")
        out["c_multiplier"] = np.full(n, float(multiplier))
    out["set_index"] = np.repeat(np.arange(n_sets, dtype=np.int64), k)
    if scene.source.kind == "multi_sersic":
        # Drawn after everything else, so the other kinds' streams are unchanged.
        out.update(_sample_multi_sersic(scene.source, drawn, n, rng))
    if scene.lens_light.joint is not None:
        light = _sample_joint_light(scene.lens_light, n, rng)
        if comp.lens_light:
            out.update(light)
    if comp.sky:  # last: a scene without sky draws the same stream as before
        out["sky_level"] = scene.sky.level.sample(rng, n)
    return out


def _sample_joint_light(
    light: LensLightSpec, n: int, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Lens-light keys from the joint prior (:class:`LensLightSpec`): (mag, ln R, n, q)
    jointly, then the position angle φ ~ U[0, π)."""
    assert light.joint is not None
    draw = light.joint.sample(rng, n)
    phi = rng.uniform(0.0, math.pi, n)
    e = (1.0 - draw["q"]) / (1.0 + draw["q"])
    return {
        "light_mag": draw["mag"],
        "light_r": np.exp(draw["ln_r"]),
        "light_n": draw["n"],
        "light_e1": e * np.cos(2.0 * phi),
        "light_e2": e * np.sin(2.0 * phi),
    }


def _sample_multi_sersic(
    src: SourceSpec, drawn: dict[str, np.ndarray], n: int, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Multi-Sérsic keys (:func:`multi_sersic_keys`): body = the Sérsic draw, then clumps."""
    ms = src.multi_sersic
    kmax = ms.max_components
    ncomp = np.rint(ms.n_components.sample(rng, n)).astype(np.int64)
    out: dict[str, np.ndarray] = {"src_mag_total": drawn["src_mag"], "src_ncomp": ncomp}
    weights = np.zeros((kmax, n))
    weights[0] = 1.0
    comps = [
        {
            "r": drawn["src_r"],
            "n": drawn["src_n"],
            "e1": drawn["src_e1"],
            "e2": drawn["src_e2"],
            "dx": np.zeros(n),
            "dy": np.zeros(n),
        }
    ]
    for j in range(1, kmax):  # every slot drawn for every image: fixed stream layout
        share = ms.share.sample(rng, n)
        c = {
            p: getattr(ms, a).sample(rng, n)
            for p, a in (("r", "r_sersic"), ("n", "n_sersic"), ("e1", "e1"), ("e2", "e2"))
        }
        rad, ang = ms.offset.sample(rng, n), ms.offset_angle.sample(rng, n)
        c["dx"], c["dy"] = rad * np.cos(ang), rad * np.sin(ang)
        weights[j] = np.where(j < ncomp, share, 0.0)
        comps.append(c)
    frac = weights / weights.sum(axis=0)
    for j, c in enumerate(comps):
        out[f"src_frac_{j}"] = frac[j]
        for p in MULTI_SERSIC_KEYS[1:]:
            out[f"src_{p}_{j}"] = c[p]
    return out
