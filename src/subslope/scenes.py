"""Scene specifications and the sampling of per-image (macro) parameters.

A *scene* is everything needed to draw the parameters of one family of simulated images:
which components are on, the prior of every parameter of Table 1 of the reference paper
(SCIENCE.md §3), the subhalo and line-of-sight (LoS) models, the source kind and how
many images share one label γ (``images_per_set``). Scenes are declared in the config
under ``scenes.<name>``; each entry is merged key by key onto a *preset*:

- ``train``: the paper's training scene (N_sub ~ U{0, 3000}, COSMOS training sources);
- ``validation``: as ``train`` but N_sub ~ U{0, 1800} and validation sources;
- ``test_epl``: as ``validation`` with test sources and sets of 13 images sharing γ;
- ``nfw`` / ``tnfw``: the CDM test sets: NFW / truncated-NFW subhalos placed everywhere,
  NFW LoS halos, concentration = a × c_CDM(M, z) × 10^N(0, 0.1 dex), sets of 13 images;
- any other name starts from the ``train`` preset.

A prior entry (a mapping with ``dist``) replaces the preset's prior as a whole; every
other mapping is merged key by key. Unknown keys raise :class:`SceneError` naming the
full key (``scenes.train.main_lens.theta_ee``).

:func:`sample_macro` draws every per-image parameter as float64 numpy arrays (integers
for ``n_sub`` and ``set_index``). All parameters are drawn in a fixed order whether or
not their component is on, then the parameters of switched-off components are dropped
from the result; so switching a component off never changes the other draws.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from subslope.priors import PowerLaw, Prior, PriorError

__all__ = [
    "SceneError",
    "SUBHALO_PROFILES",
    "LOS_PROFILES",
    "PLACEMENTS",
    "SOURCE_KINDS",
    "COSMOS_SPLITS",
    "PAPER_SCENE",
    "PRESETS",
    "Components",
    "Redshifts",
    "SourceSpec",
    "MultiSersicSpec",
    "MAX_SOURCE_COMPONENTS",
    "MULTI_SERSIC_KEYS",
    "multi_sersic_keys",
    "MainLensSpec",
    "MultipoleSpec",
    "ShearSpec",
    "LensLightSpec",
    "SubhaloSpec",
    "LosSpec",
    "ConcentrationSpec",
    "Scene",
    "preset",
    "scenes_from_config",
    "sample_macro",
]

SUBHALO_PROFILES = ("epl", "nfw", "tnfw")
LOS_PROFILES = ("epl", "nfw")
PLACEMENTS = ("arc", "everywhere")
SOURCE_KINDS = ("cosmos", "sersic", "multi_sersic")
#: Largest number of components of the multi-Sérsic source (the upper end of the
#: ``source.multi_sersic.n_components`` support may not exceed it).
MAX_SOURCE_COMPONENTS = 8
#: Per-component macro keys of the multi-Sérsic source (``src_<name>_<k>``).
MULTI_SERSIC_KEYS = ("frac", "r", "n", "e1", "e2", "dx", "dy")
COSMOS_SPLITS = ("train", "validation", "test")


class SceneError(PriorError):
    """A scene configuration is malformed; the message names the config key."""


def _u(low, high):
    return {"dist": "uniform", "low": low, "high": high}


def _n(mean, std, low=None, high=None):
    out = {"dist": "normal", "mean": mean, "std": std}
    if low is not None:
        out["low"] = low
    if high is not None:
        out["high"] = high
    return out


#: The training scene of the reference paper (SCIENCE.md §3). Where the paper and its
#: public code disagree, the paper's value is used (comments give the code's value).
PAPER_SCENE: dict[str, Any] = {
    "components": {"lens_light": True, "multipoles": True, "shear": True, "subhalos": True, "los": True},
    "images_per_set": 1,
    "redshifts": {"z_lens": _u(0.15, 0.25), "z_source": _u(0.5, 0.7)},
    "source": {
        "kind": "cosmos",
        "split": "train",
        "x": _u(-0.1, 0.1),
        "y": _u(-0.1, 0.1),
        "rotation": _u(-math.pi, math.pi),
        # Parametric Sérsic source (kind: sersic only; not part of the paper).
        "mag": _u(20.0, 23.0),
        "r_sersic": _u(0.1, 0.4),
        "n_sersic": _u(0.8, 3.0),
        "e1": _u(-0.3, 0.3),
        "e2": _u(-0.3, 0.3),
        # Multi-Sérsic source (kind: multi_sersic only; not part of the paper): a main body
        # (component 0: the Sérsic priors above, weight 1, at the source centre) plus
        # n_components − 1 compact clumps (priors below), total magnitude from `mag`.
        "multi_sersic": {
            "n_components": {"dist": "uniform_int", "low": 1, "high": 4},
            "share": _u(0.1, 0.6),
            "r_sersic": _u(0.02, 0.1),
            "n_sersic": _u(0.5, 1.5),
            "e1": _u(-0.2, 0.2),
            "e2": _u(-0.2, 0.2),
            "offset": _u(0.05, 0.35),
            "offset_angle": _u(-math.pi, math.pi),
        },
    },
    "main_lens": {
        "x": _u(-0.2, 0.2),
        "y": _u(-0.2, 0.2),
        "theta_e": _u(0.9, 1.3),
        "e1": _u(-0.2, 0.2),
        "e2": _u(-0.2, 0.2),
        "gamma": _n(2.0, 0.1, 1.1, 2.9),  # public code: std 0.2
    },
    "multipoles": {
        "a3": _u(0.0, 0.05),
        "phi3": _u(-math.pi, math.pi),
        "a4": _u(0.0, 0.05),
        "phi4": _u(-math.pi, math.pi),
    },
    "shear": {"g1": _u(-0.1, 0.1), "g2": _u(-0.1, 0.1)},
    "lens_light": {
        "mag": _u(17.0, 19.0),  # public code: U(16, 19)
        "r_sersic": _n(0.8, 0.15, low=0.01),  # keep > 0
        "n_sersic": _n(2.0, 0.5, 0.5, 8.0),  # public code: U(1, 4)
        "e1": _u(-0.1, 0.1),
        "e2": _u(-0.1, 0.1),
    },
    "subhalos": {
        "count": {"dist": "uniform_int", "low": 0, "high": 3000},
        "mass": {"slope": -1.9, "m_min": 1.0e7, "m_max": 1.0e10},
        "gamma": _u(1.1, 2.9),
        "gamma_scatter": 0.1,
        "gamma_bounds": [1.01, 2.99],
        "e1": _u(-0.2, 0.2),
        "e2": _u(-0.2, 0.2),
        "profile": "epl",
        "placement": "arc",
        "threshold_fraction": 0.2,  # public code: 0.5
    },
    "los": {"delta_los": _u(0.0, 2.0), "profile": "epl", "m_min": 1.0e7, "m_max": 1.0e10},
    "concentration": {"multipliers": [0.5, 1.0, 2.0, 4.0, 8.0], "scatter_dex": 0.1, "apply_to_los": False},
}

_EVAL = {"subhalos": {"count": {"dist": "uniform_int", "low": 0, "high": 1800}}}
_CDM = {
    "images_per_set": 13,
    "source": {"split": "test"},
    "subhalos": {"count": {"dist": "uniform_int", "low": 0, "high": 1800}, "placement": "everywhere"},
    "los": {"profile": "nfw"},
}

#: Overrides of :data:`PAPER_SCENE` for the named scenes.
PRESETS: dict[str, dict[str, Any]] = {
    "train": {},
    "validation": {**_EVAL, "source": {"split": "validation"}},
    "test_epl": {**_EVAL, "images_per_set": 13, "source": {"split": "test"}},
    "nfw": {**_CDM, "subhalos": {**_CDM["subhalos"], "profile": "nfw"}},
    "tnfw": {**_CDM, "subhalos": {**_CDM["subhalos"], "profile": "tnfw"}},
}


def _is_prior(d: Any) -> bool:
    return isinstance(d, Mapping) and "dist" in d


def _merge(base: dict[str, Any], over: Mapping[str, Any], key: str) -> dict[str, Any]:
    """Merge ``over`` onto ``base``; unknown keys raise; prior mappings replace whole."""
    if not isinstance(over, Mapping):
        raise SceneError(f"config key {key} = {over!r} must be a mapping")
    out = copy.deepcopy(base)
    for k, v in over.items():
        sub = f"{key}.{k}"
        if k not in base:
            raise SceneError(
                f"unknown config key {sub}; allowed keys at {key}: {', '.join(sorted(base))}"
            )
        if isinstance(base[k], Mapping) and not _is_prior(base[k]) and isinstance(v, Mapping):
            out[k] = _merge(base[k], v, sub)
        else:
            out[k] = copy.deepcopy(v)
    return out


def preset(name: str) -> dict[str, Any]:
    """Complete config mapping of the preset scene ``name`` (``train`` for other names)."""
    return _merge(PAPER_SCENE, PRESETS.get(name, {}), f"scenes.{name}")


# ---------------------------------------------------------------------------- specs
def _prior(d: Mapping[str, Any], k: str, key: str) -> Prior:
    return Prior.from_config(d[k], f"{key}.{k}")


def _choice(value: Any, allowed: tuple[str, ...], key: str) -> str:
    if value not in allowed:
        raise SceneError(f"config key {key} = {value!r} is not allowed; allowed: {', '.join(allowed)}")
    return value


def _real(value: Any, key: str, lo: float, hi: float, lo_open=False, hi_open=False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        left, right = "(" if lo_open else "[", ")" if hi_open else "]"
        raise SceneError(f"config key {key} = {value!r} must be a number in {left}{lo}, {hi}{right}")
    return float(value)


def _bool(value: Any, key: str) -> bool:
    if not isinstance(value, bool):
        raise SceneError(f"config key {key} = {value!r} must be true or false")
    return value


def _within(p: Prior, key: str, lo: float, hi: float) -> Prior:
    s_lo, s_hi = p.support
    if s_lo < lo or s_hi > hi:
        raise SceneError(
            f"config key {key}: support [{s_lo}, {s_hi}] of the prior must lie within [{lo}, {hi}]"
        )
    return p


def _multi_sersic(d: Any, key: str) -> MultiSersicSpec:
    if not isinstance(d, Mapping):
        raise SceneError(f"config key {key} = {d!r} must be a mapping")
    spec = MultiSersicSpec(**{p: _prior(d, p, key) for p in (
        "n_components", "share", "r_sersic", "n_sersic", "e1", "e2", "offset", "offset_angle")})
    nc = spec.n_components
    lo, hi = nc.support
    if nc.dist not in ("uniform_int", "fixed") or lo != int(lo) or hi != int(hi) or lo < 1 \
            or hi > MAX_SOURCE_COMPONENTS:
        raise SceneError(f"config key {key}.n_components must be a uniform_int prior or a fixed integer "
                         f"within [1, {MAX_SOURCE_COMPONENTS}]")
    _within(spec.share, f"{key}.share", 0.0, math.inf)
    _within(spec.r_sersic, f"{key}.r_sersic", 1e-6, math.inf)
    _within(spec.n_sersic, f"{key}.n_sersic", 0.2, 10.0)
    for p in ("e1", "e2"):
        _within(getattr(spec, p), f"{key}.{p}", -0.9, 0.9)
    _within(spec.offset, f"{key}.offset", 0.0, math.inf)
    return spec


@dataclass(frozen=True)
class Components:
    """Which optional components are rendered (main lens and source are always on)."""

    lens_light: bool = True
    multipoles: bool = True
    shear: bool = True
    subhalos: bool = True
    los: bool = True


@dataclass(frozen=True)
class Redshifts:
    z_lens: Prior
    z_source: Prior


@dataclass(frozen=True)
class MultiSersicSpec:
    """Clumps of the multi-Sérsic source (``source.kind = 'multi_sersic'``).

    ``n_components`` (integer prior, support within [1, MAX_SOURCE_COMPONENTS]) counts the
    main body plus the clumps. Each clump k ≥ 1 draws an unnormalised flux weight
    ``share`` (the body's weight is 1), ``r_sersic`` (arcsec), ``n_sersic``, ``e1``,
    ``e2`` and a centre ``offset`` (arcsec) at ``offset_angle`` (rad) from the source
    centre, in the source's own frame (rotated with it by ``src_rotation``).
    """

    n_components: Prior
    share: Prior
    r_sersic: Prior
    n_sersic: Prior
    e1: Prior
    e2: Prior
    offset: Prior
    offset_angle: Prior

    @property
    def max_components(self) -> int:
        """K: the number of component slots stored per image (top of the count support)."""
        return int(self.n_components.support[1])


def multi_sersic_keys(max_components: int) -> list[str]:
    """Macro keys of a multi-Sérsic source with ``max_components`` slots, in drawing order."""
    return ["src_mag_total", "src_ncomp"] + [
        f"src_{name}_{k}" for k in range(max_components) for name in MULTI_SERSIC_KEYS
    ]


@dataclass(frozen=True)
class SourceSpec:
    """Source light: a COSMOS galaxy of ``split``, a parametric Sérsic or a multi-Sérsic.

    ``x``, ``y`` (arcsec) and ``rotation`` (rad) apply to every kind; ``mag``,
    ``r_sersic`` (arcsec), ``n_sersic``, ``e1``, ``e2`` to ``kind='sersic'`` and, as the
    total magnitude and the main body, to ``kind='multi_sersic'``, whose clumps follow
    ``multi_sersic``.
    """

    kind: str
    split: str
    x: Prior
    y: Prior
    rotation: Prior
    mag: Prior
    r_sersic: Prior
    n_sersic: Prior
    e1: Prior
    e2: Prior
    multi_sersic: MultiSersicSpec


@dataclass(frozen=True)
class MainLensSpec:
    """Main-lens EPL: centre (arcsec), Einstein radius (arcsec), e1, e2, slope γ_ML."""

    x: Prior
    y: Prior
    theta_e: Prior
    e1: Prior
    e2: Prior
    gamma: Prior


@dataclass(frozen=True)
class MultipoleSpec:
    """m = 3, 4 multipole strengths a_m and angles φ_m (rad), centred on the lens."""

    a3: Prior
    phi3: Prior
    a4: Prior
    phi4: Prior


@dataclass(frozen=True)
class ShearSpec:
    g1: Prior
    g2: Prior


@dataclass(frozen=True)
class LensLightSpec:
    """Elliptical Sérsic lens light centred on the lens (AB mag, arcsec)."""

    mag: Prior
    r_sersic: Prior
    n_sersic: Prior
    e1: Prior
    e2: Prior


@dataclass(frozen=True)
class SubhaloSpec:
    """Subhalo population model.

    ``gamma`` is the prior of the per-system label γ; per subhalo
    γ_i ~ N(γ, gamma_scatter·γ) truncated to ``gamma_bounds``. ``threshold_fraction`` is
    used by ``placement='arc'`` only.
    """

    count: Prior
    mass: PowerLaw
    gamma: Prior
    gamma_scatter: float
    gamma_bounds: tuple[float, float]
    e1: Prior
    e2: Prior
    profile: str
    placement: str
    threshold_fraction: float


@dataclass(frozen=True)
class LosSpec:
    """Line-of-sight halos: mass-function normalisation δ_los and profile."""

    delta_los: Prior
    profile: str
    m_min: float
    m_max: float


@dataclass(frozen=True)
class ConcentrationSpec:
    """CDM concentration: c = a · c_DM14(M, z) · 10^N(0, scatter_dex)."""

    multipliers: tuple[float, ...]
    scatter_dex: float
    apply_to_los: bool


@dataclass(frozen=True)
class Scene:
    """Complete specification of one family of simulated images."""

    name: str
    components: Components
    images_per_set: int
    redshifts: Redshifts
    source: SourceSpec
    main_lens: MainLensSpec
    multipoles: MultipoleSpec
    shear: ShearSpec
    lens_light: LensLightSpec
    subhalos: SubhaloSpec
    los: LosSpec
    concentration: ConcentrationSpec

    @property
    def has_label(self) -> bool:
        """True when images carry the label γ (EPL subhalos or EPL LoS halos are on)."""
        c = self.components
        return (c.subhalos and self.subhalos.profile == "epl") or (c.los and self.los.profile == "epl")

    @property
    def uses_concentration(self) -> bool:
        """True when some active component is NFW/tNFW (a CDM scene)."""
        c = self.components
        return (c.subhalos and self.subhalos.profile != "epl") or (c.los and self.los.profile == "nfw")

    @classmethod
    def from_config(cls, name: str, spec: Mapping[str, Any] | None = None, key: str | None = None) -> Scene:
        """Build a scene from its config mapping merged onto the preset for ``name``."""
        key = key or f"scenes.{name}"
        if not isinstance(name, str) or not name:
            raise SceneError(f"scene name {name!r} must be a non-empty string")
        d = _merge(preset(name), spec or {}, key)

        comp = Components(**{k: _bool(v, f"{key}.components.{k}") for k, v in d["components"].items()})
        ips = d["images_per_set"]
        if isinstance(ips, bool) or not isinstance(ips, int) or not 1 <= ips <= 1000:
            raise SceneError(f"config key {key}.images_per_set = {ips!r} must be an integer in [1, 1000]")

        k = f"{key}.redshifts"
        z = Redshifts(_prior(d["redshifts"], "z_lens", k), _prior(d["redshifts"], "z_source", k))
        _within(z.z_lens, f"{k}.z_lens", 0.0, 10.0)
        _within(z.z_source, f"{k}.z_source", 0.0, 10.0)
        if z.z_source.support[0] <= z.z_lens.support[1]:
            raise SceneError(
                f"config key {k}: z_source support {z.z_source.support} must lie above the "
                f"z_lens support {z.z_lens.support}"
            )

        s, k = d["source"], f"{key}.source"
        src = SourceSpec(
            kind=_choice(s["kind"], SOURCE_KINDS, f"{k}.kind"),
            split=_choice(s["split"], COSMOS_SPLITS, f"{k}.split"),
            **{p: _prior(s, p, k) for p in ("x", "y", "rotation", "mag", "r_sersic", "n_sersic", "e1", "e2")},
            multi_sersic=_multi_sersic(s["multi_sersic"], f"{k}.multi_sersic"),
        )
        _within(src.r_sersic, f"{k}.r_sersic", 1e-6, math.inf)
        _within(src.n_sersic, f"{k}.n_sersic", 0.2, 10.0)

        m, k = d["main_lens"], f"{key}.main_lens"
        main = MainLensSpec(**{p: _prior(m, p, k) for p in ("x", "y", "theta_e", "e1", "e2", "gamma")})
        _within(main.theta_e, f"{k}.theta_e", 1e-6, math.inf)
        _within(main.gamma, f"{k}.gamma", 1.0, 3.0)
        for p in ("e1", "e2"):
            _within(getattr(main, p), f"{k}.{p}", -1.0, 1.0)

        mp = MultipoleSpec(**{p: _prior(d["multipoles"], p, f"{key}.multipoles") for p in ("a3", "phi3", "a4", "phi4")})
        sh = ShearSpec(**{p: _prior(d["shear"], p, f"{key}.shear") for p in ("g1", "g2")})

        ll, k = d["lens_light"], f"{key}.lens_light"
        light = LensLightSpec(**{p: _prior(ll, p, k) for p in ("mag", "r_sersic", "n_sersic", "e1", "e2")})
        _within(light.r_sersic, f"{k}.r_sersic", 1e-6, math.inf)
        _within(light.n_sersic, f"{k}.n_sersic", 0.2, 10.0)

        sub, k = d["subhalos"], f"{key}.subhalos"
        count = _prior(sub, "count", k)
        if count.dist not in ("uniform_int", "fixed") or count.support[0] < 0 or (
            count.dist == "fixed" and count.support[0] != int(count.support[0])
        ):
            raise SceneError(
                f"config key {k}.count must be a uniform_int prior or a fixed non-negative integer"
            )
        mass = sub["mass"]
        if not isinstance(mass, Mapping) or set(mass) != {"slope", "m_min", "m_max"}:
            raise SceneError(f"config key {k}.mass = {mass!r} must be a mapping with keys slope, m_min, m_max")
        mass_prior = Prior.from_config(
            {"dist": "power_law", "slope": mass["slope"], "low": mass["m_min"], "high": mass["m_max"]}, f"{k}.mass"
        )
        _within(mass_prior, f"{k}.mass", 1e3, 1e15)
        bounds = sub["gamma_bounds"]
        if not (isinstance(bounds, (list, tuple)) and len(bounds) == 2):
            raise SceneError(f"config key {k}.gamma_bounds = {bounds!r} must be a list [low, high]")
        lo = _real(bounds[0], f"{k}.gamma_bounds[0]", 1.0, 3.0, lo_open=True, hi_open=True)
        hi = _real(bounds[1], f"{k}.gamma_bounds[1]", 1.0, 3.0, lo_open=True, hi_open=True)
        if lo >= hi:
            raise SceneError(f"config key {k}.gamma_bounds = {bounds!r} needs low < high")
        gamma = _within(_prior(sub, "gamma", k), f"{k}.gamma", lo, hi)
        subs = SubhaloSpec(
            count=count,
            mass=mass_prior,
            gamma=gamma,
            gamma_scatter=_real(sub["gamma_scatter"], f"{k}.gamma_scatter", 0.0, 1.0),
            gamma_bounds=(lo, hi),
            e1=_within(_prior(sub, "e1", k), f"{k}.e1", -1.0, 1.0),
            e2=_within(_prior(sub, "e2", k), f"{k}.e2", -1.0, 1.0),
            profile=_choice(sub["profile"], SUBHALO_PROFILES, f"{k}.profile"),
            placement=_choice(sub["placement"], PLACEMENTS, f"{k}.placement"),
            threshold_fraction=_real(sub["threshold_fraction"], f"{k}.threshold_fraction", 0.0, 1.0, True, True),
        )

        lo_d, k = d["los"], f"{key}.los"
        los = LosSpec(
            delta_los=_within(_prior(lo_d, "delta_los", k), f"{k}.delta_los", 0.0, 100.0),
            profile=_choice(lo_d["profile"], LOS_PROFILES, f"{k}.profile"),
            m_min=_real(lo_d["m_min"], f"{k}.m_min", 1e3, 1e15),
            m_max=_real(lo_d["m_max"], f"{k}.m_max", 1e3, 1e15),
        )
        if los.m_min >= los.m_max:
            raise SceneError(f"config key {k}.m_min = {los.m_min!r} must be < {k}.m_max = {los.m_max!r}")

        c, k = d["concentration"], f"{key}.concentration"
        mult = c["multipliers"]
        if not isinstance(mult, (list, tuple)) or not mult:
            raise SceneError(f"config key {k}.multipliers = {mult!r} must be a non-empty list of numbers > 0")
        conc = ConcentrationSpec(
            multipliers=tuple(_real(a, f"{k}.multipliers[{i}]", 0.0, 1e3, lo_open=True) for i, a in enumerate(mult)),
            scatter_dex=_real(c["scatter_dex"], f"{k}.scatter_dex", 0.0, 1.0),
            apply_to_los=_bool(c["apply_to_los"], f"{k}.apply_to_los"),
        )
        return cls(name, comp, ips, z, src, main, mp, sh, light, subs, los, conc)


def scenes_from_config(scenes: Mapping[str, Any] | None, key: str = "scenes") -> dict[str, Scene]:
    """All scenes of the config's ``scenes`` block; the five presets are always present."""
    scenes = dict(scenes or {})
    if not all(isinstance(v, Mapping) or v is None for v in scenes.values()):
        bad = [n for n, v in scenes.items() if not (isinstance(v, Mapping) or v is None)]
        raise SceneError(f"config key {key}.{bad[0]} must be a mapping")
    names = list(PRESETS) + [n for n in scenes if n not in PRESETS]
    return {n: Scene.from_config(n, scenes.get(n) or {}, f"{key}.{n}") for n in names}


# ---------------------------------------------------------------------------- sampling
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
        ``c_multiplier`` (CDM scenes) and ``set_index`` (int64). Lens light is centred
        on ``lens_x, lens_y``. Keys of switched-off components are absent.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n = {n!r} must be a positive integer number of images")
    k = scene.images_per_set
    if n % k:
        raise ValueError(f"n = {n} must be a multiple of images_per_set = {k} of scene {scene.name!r}")
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
        if not (isinstance(multiplier, (int, float)) and math.isfinite(multiplier) and multiplier > 0):
            raise ValueError(f"multiplier = {multiplier!r} must be a finite number > 0")
        out["c_multiplier"] = np.full(n, float(multiplier))
    out["set_index"] = np.repeat(np.arange(n_sets, dtype=np.int64), k)
    if scene.source.kind == "multi_sersic":
        # Drawn after everything else, so the other kinds' streams are unchanged.
        out.update(_sample_multi_sersic(scene.source, drawn, n, rng))
    return out


def _sample_multi_sersic(src: SourceSpec, drawn: dict[str, np.ndarray], n: int,
                         rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Multi-Sérsic keys (:func:`multi_sersic_keys`): body = the Sérsic draw, then clumps."""
    ms = src.multi_sersic
    kmax = ms.max_components
    ncomp = np.rint(ms.n_components.sample(rng, n)).astype(np.int64)
    out: dict[str, np.ndarray] = {"src_mag_total": drawn["src_mag"], "src_ncomp": ncomp}
    weights = np.zeros((kmax, n))
    weights[0] = 1.0
    comps = [{"r": drawn["src_r"], "n": drawn["src_n"], "e1": drawn["src_e1"], "e2": drawn["src_e2"],
              "dx": np.zeros(n), "dy": np.zeros(n)}]
    for j in range(1, kmax):  # every slot drawn for every image: fixed stream layout
        share = ms.share.sample(rng, n)
        c = {p: getattr(ms, a).sample(rng, n) for p, a in
             (("r", "r_sersic"), ("n", "n_sersic"), ("e1", "e1"), ("e2", "e2"))}
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

