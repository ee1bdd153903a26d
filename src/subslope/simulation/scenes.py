"""Scene specifications: what a family of simulated images is drawn from.

A *scene* is everything needed to draw the parameters of one family of simulated images:
which components are on, the prior of every parameter of Table 1 of the reference paper
(docs/simulation.md), the subhalo and line-of-sight (LoS) models, the source kind and how
many images share one label γ (``images_per_set``). Scenes are declared in the config
under ``scenes.<name>``; each entry is merged key by key onto a *preset* of
``schemas/scene_presets.yaml`` (``train``, ``validation``, ``test_epl``, ``nfw``,
``tnfw``; any other name starts from the paper's training scene).

A prior entry (a mapping with ``dist``) replaces the preset's prior as a whole; every
other mapping is merged key by key. Unknown keys raise :class:`SceneError` naming the
full key (``scenes.train.main_lens.theta_ee``).

:func:`subslope.simulation.macro.sample_macro` draws the per-image parameters of a scene.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from subslope.simulation.presets import (
    PAPER_SCENE,
    PRESETS,
    merge_onto_preset,
    preset,
)
from subslope.simulation.priors import JointNormal, PowerLaw, Prior
from subslope.simulation.spec_checks import SceneError
from subslope.simulation.spec_checks import boolean as _bool
from subslope.simulation.spec_checks import choice as _choice
from subslope.simulation.spec_checks import prior_at as _prior
from subslope.simulation.spec_checks import real as _real
from subslope.simulation.spec_checks import within as _within

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
    "JOINT_LIGHT_NAMES",
    "SkySpec",
    "SubhaloSpec",
    "LosSpec",
    "ConcentrationSpec",
    "Scene",
    "preset",
    "scenes_from_config",
    "merge_onto_preset",
]

SUBHALO_PROFILES = ("epl", "nfw", "tnfw")
LOS_PROFILES = ("epl", "nfw")
PLACEMENTS = ("arc", "landing", "everywhere")
SHEET_CENTRES = ("origin", "mass_centroid")  # as subslope.render.populations
SOURCE_KINDS = ("cosmos", "sersic", "multi_sersic")
#: Largest number of components of the multi-Sérsic source (the upper end of the
#: ``source.multi_sersic.n_components`` support may not exceed it).
MAX_SOURCE_COMPONENTS = 8
#: Per-component macro keys of the multi-Sérsic source (``src_<name>_<k>``).
MULTI_SERSIC_KEYS = ("frac", "r", "n", "e1", "e2", "dx", "dy")
COSMOS_SPLITS = ("train", "validation", "test")


# ---------------------------------------------------------------------------- specs
def _multi_sersic(d: Any, key: str) -> MultiSersicSpec:
    if not isinstance(d, Mapping):
        raise SceneError(f"config key {key} = {d!r} must be a mapping")
    spec = MultiSersicSpec(
        **{
            p: _prior(d, p, key)
            for p in (
                "n_components",
                "share",
                "r_sersic",
                "n_sersic",
                "e1",
                "e2",
                "offset",
                "offset_angle",
            )
        }
    )
    nc = spec.n_components
    lo, hi = nc.support
    if (
        nc.dist not in ("uniform_int", "fixed")
        or lo != int(lo)
        or hi != int(hi)
        or lo < 1
        or hi > MAX_SOURCE_COMPONENTS
    ):
        raise SceneError(
            f"config key {key}.n_components must be a uniform_int prior or a fixed integer "
            f"within [1, {MAX_SOURCE_COMPONENTS}]"
        )
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
    sky: bool = False


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


#: Parameters of the joint lens-light prior, in this order: AB magnitude, ln of the
#: half-light radius (ln arcsec), Sérsic index and axis ratio.
JOINT_LIGHT_NAMES = ("mag", "ln_r", "n", "q")


@dataclass(frozen=True)
class LensLightSpec:
    """Elliptical Sérsic lens light centred on the lens (AB mag, arcsec).

    With ``joint`` set, (mag, ln R, n, q) are drawn together from that multivariate
    normal (:data:`JOINT_LIGHT_NAMES`) and the position angle uniformly in [0, π), and
    the five one-dimensional priors are not used; e = (1 − q)/(1 + q),
    (e1, e2) = e (cos 2φ, sin 2φ)."""

    mag: Prior
    r_sersic: Prior
    n_sersic: Prior
    e1: Prior
    e2: Prior
    joint: JointNormal | None = None


@dataclass(frozen=True)
class SkySpec:
    """A constant sky level per image (e⁻/s per pixel), added after the PSF: what the
    sky subtraction of real cutouts leaves (``components.sky``)."""

    level: Prior


@dataclass(frozen=True)
class SubhaloSpec:
    """Subhalo population model.

    ``gamma`` is the prior of the per-system label γ; per subhalo
    γ_i ~ N(γ, gamma_scatter·γ) truncated to ``gamma_bounds``. ``threshold_fraction`` is
    used by ``placement='arc'`` (of the smooth model's maximum) and ``'landing'`` (of the
    maximum of the image of the source stamp's support) only; ``sheet_centre``:
    ``origin`` | ``mass_centroid``.
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
    sheet_centre: str = "mass_centroid"
    fixed_gamma: float | None = None


@dataclass(frozen=True)
class LosSpec:
    """Line-of-sight halos: δ_los, profile, mass range, sheet centre (as subhalos')."""

    delta_los: Prior
    profile: str
    m_min: float
    m_max: float
    sheet_centre: str = "mass_centroid"


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
    sky: SkySpec
    common_draws: bool = False

    @property
    def has_label(self) -> bool:
        """True when images carry the label γ (EPL subhalos or EPL LoS halos are on)."""
        c = self.components
        return (c.subhalos and self.subhalos.profile == "epl") or (
            c.los and self.los.profile == "epl"
        )

    @property
    def uses_concentration(self) -> bool:
        """True when the concentration multiplier a acts on some active component (a CDM
        scene, simulated once per multiplier): NFW/tNFW subhalos, or NFW LoS halos with
        ``concentration.apply_to_los``. NFW LoS halos alone draw a = 1 concentrations."""
        c = self.components
        return (c.subhalos and self.subhalos.profile != "epl") or (
            c.los and self.los.profile == "nfw" and self.concentration.apply_to_los
        )

    @classmethod
    def from_config(
        cls, name: str, spec: Mapping[str, Any] | None = None, key: str | None = None
    ) -> Scene:
        """Build a scene from its config mapping merged onto the preset for ``name``."""
        key = key or f"scenes.{name}"
        if not isinstance(name, str) or not name:
            raise SceneError(f"scene name {name!r} must be a non-empty string")
        d = merge_onto_preset(name, spec, key)
        comp = Components(
            **{k: _bool(v, f"{key}.components.{k}") for k, v in d["components"].items()}
        )
        ips = d["images_per_set"]
        if isinstance(ips, bool) or not isinstance(ips, int) or not 1 <= ips <= 1000:
            raise SceneError(
                f"config key {key}.images_per_set = {ips!r} must be an integer in [1, 1000]"
            )
        mp = MultipoleSpec(
            **{
                p: _prior(d["multipoles"], p, f"{key}.multipoles")
                for p in ("a3", "phi3", "a4", "phi4")
            }
        )
        sh = ShearSpec(**{p: _prior(d["shear"], p, f"{key}.shear") for p in ("g1", "g2")})
        source = _source_spec(d["source"], f"{key}.source")
        subhalos = _subhalo_spec(d["subhalos"], f"{key}.subhalos")
        if subhalos.placement == "landing" and source.kind != "cosmos":
            raise SceneError(
                f"config key {key}.subhalos.placement = 'landing' needs a COSMOS stamp to "
                f"land (source.kind: cosmos), got {key}.source.kind = {source.kind!r}; "
                "use 'arc' or 'everywhere'"
            )
        return cls(
            name,
            comp,
            ips,
            _redshifts_spec(d["redshifts"], f"{key}.redshifts"),
            source,
            _main_lens_spec(d["main_lens"], f"{key}.main_lens"),
            mp,
            sh,
            _lens_light_spec(d["lens_light"], f"{key}.lens_light"),
            subhalos,
            _los_spec(d["los"], f"{key}.los"),
            _concentration_spec(d["concentration"], f"{key}.concentration"),
            SkySpec(_prior(d["sky"], "level", f"{key}.sky")),
            _bool(d.get("common_draws", False), f"{key}.common_draws"),
        )


# ----------------------------------------------------------------- sections of a scene
def _redshifts_spec(r: Mapping[str, Any], k: str) -> Redshifts:
    z = Redshifts(_prior(r, "z_lens", k), _prior(r, "z_source", k))
    _within(z.z_lens, f"{k}.z_lens", 0.0, 10.0)
    _within(z.z_source, f"{k}.z_source", 0.0, 10.0)
    if z.z_source.support[0] <= z.z_lens.support[1]:
        raise SceneError(
            f"config key {k}: z_source support {z.z_source.support} must lie above the "
            f"z_lens support {z.z_lens.support}"
        )
    return z


def _source_spec(s: Mapping[str, Any], k: str) -> SourceSpec:
    src = SourceSpec(
        kind=_choice(s["kind"], SOURCE_KINDS, f"{k}.kind"),
        split=_choice(s["split"], COSMOS_SPLITS, f"{k}.split"),
        **{
            p: _prior(s, p, k)
            for p in ("x", "y", "rotation", "mag", "r_sersic", "n_sersic", "e1", "e2")
        },
        multi_sersic=_multi_sersic(s["multi_sersic"], f"{k}.multi_sersic"),
    )
    _within(src.r_sersic, f"{k}.r_sersic", 1e-6, math.inf)
    _within(src.n_sersic, f"{k}.n_sersic", 0.2, 10.0)
    return src


def _main_lens_spec(m: Mapping[str, Any], k: str) -> MainLensSpec:
    main = MainLensSpec(**{p: _prior(m, p, k) for p in ("x", "y", "theta_e", "e1", "e2", "gamma")})
    _within(main.theta_e, f"{k}.theta_e", 1e-6, math.inf)
    _within(main.gamma, f"{k}.gamma", 1.0, 3.0, open_=True)  # the EPL needs 1 < γ < 3
    for p in ("e1", "e2"):
        _within(getattr(main, p), f"{k}.{p}", -1.0, 1.0)
    return main


def _lens_light_spec(ll: Mapping[str, Any], k: str) -> LensLightSpec:
    joint = None
    if ll.get("joint") is not None:
        joint = JointNormal.from_config(ll["joint"], f"{k}.joint", JOINT_LIGHT_NAMES)
        for name, lo, hi in (("n", 0.2, 10.0), ("q", 0.05, 1.0)):
            i = JOINT_LIGHT_NAMES.index(name)
            if joint.low[i] < lo or joint.high[i] > hi:
                raise SceneError(
                    f"config key {k}.joint: the box of {name} [{joint.low[i]}, "
                    f"{joint.high[i]}] must lie within [{lo}, {hi}]"
                )
    light = LensLightSpec(
        **{p: _prior(ll, p, k) for p in ("mag", "r_sersic", "n_sersic", "e1", "e2")},
        joint=joint,
    )
    _within(light.r_sersic, f"{k}.r_sersic", 1e-6, math.inf)
    _within(light.n_sersic, f"{k}.n_sersic", 0.2, 10.0)
    return light


def _subhalo_mass_prior(mass: Any, k: str) -> Prior:
    if not isinstance(mass, Mapping) or set(mass) != {"slope", "m_min", "m_max"}:
        raise SceneError(
            f"config key {k}.mass = {mass!r} must be a mapping with keys slope, m_min, m_max"
        )
    prior = Prior.from_config(
        {"dist": "power_law", "slope": mass["slope"], "low": mass["m_min"], "high": mass["m_max"]},
        f"{k}.mass",
    )
    _within(prior, f"{k}.mass", 1e3, 1e15)
    return prior


def _gamma_bounds(bounds: Any, k: str) -> tuple[float, float]:
    if not (isinstance(bounds, (list, tuple)) and len(bounds) == 2):
        raise SceneError(f"config key {k}.gamma_bounds = {bounds!r} must be a list [low, high]")
    lo = _real(bounds[0], f"{k}.gamma_bounds[0]", 1.0, 3.0, lo_open=True, hi_open=True)
    hi = _real(bounds[1], f"{k}.gamma_bounds[1]", 1.0, 3.0, lo_open=True, hi_open=True)
    if lo >= hi:
        raise SceneError(f"config key {k}.gamma_bounds = {bounds!r} needs low < high")
    return lo, hi


def _subhalo_spec(sub: Mapping[str, Any], k: str) -> SubhaloSpec:
    count = _prior(sub, "count", k)
    if (
        count.dist not in ("uniform_int", "fixed")
        or count.support[0] < 0
        or (count.dist == "fixed" and count.support[0] != int(count.support[0]))
    ):
        raise SceneError(
            f"config key {k}.count must be a uniform_int prior or a fixed non-negative integer"
        )
    mass_prior = _subhalo_mass_prior(sub["mass"], k)
    lo, hi = _gamma_bounds(sub["gamma_bounds"], k)
    gamma = _within(_prior(sub, "gamma", k), f"{k}.gamma", lo, hi)
    return SubhaloSpec(
        count=count,
        mass=mass_prior,
        gamma=gamma,
        gamma_scatter=_real(sub["gamma_scatter"], f"{k}.gamma_scatter", 0.0, 1.0),
        gamma_bounds=(lo, hi),
        e1=_within(_prior(sub, "e1", k), f"{k}.e1", -1.0, 1.0),
        e2=_within(_prior(sub, "e2", k), f"{k}.e2", -1.0, 1.0),
        profile=_choice(sub["profile"], SUBHALO_PROFILES, f"{k}.profile"),
        placement=_choice(sub["placement"], PLACEMENTS, f"{k}.placement"),
        threshold_fraction=_real(
            sub["threshold_fraction"], f"{k}.threshold_fraction", 0.0, 1.0, True, True
        ),
        sheet_centre=_choice(sub["sheet_centre"], SHEET_CENTRES, f"{k}.sheet_centre"),
        fixed_gamma=_fixed_gamma(sub, k, lo, hi),
    )


def _fixed_gamma(sub: Mapping[str, Any], k: str, lo: float, hi: float) -> float | None:
    """``subhalos.fixed_gamma`` (:data:`OPTIONAL_KEYS`): None, or a label inside the
    ``gamma`` prior's bounds for EPL subhalos."""
    value = sub.get("fixed_gamma")
    if value is None:
        return None
    if sub["profile"] != "epl":
        raise SceneError(
            f"config key {k}.fixed_gamma = {value!r} needs EPL subhalos ({k}.profile: epl), "
            f"got profile {sub['profile']!r}"
        )
    return _real(value, f"{k}.fixed_gamma", lo, hi)


def _los_spec(lo_d: Mapping[str, Any], k: str) -> LosSpec:
    los = LosSpec(
        delta_los=_within(_prior(lo_d, "delta_los", k), f"{k}.delta_los", 0.0, 100.0),
        profile=_choice(lo_d["profile"], LOS_PROFILES, f"{k}.profile"),
        m_min=_real(lo_d["m_min"], f"{k}.m_min", 1e3, 1e15),
        m_max=_real(lo_d["m_max"], f"{k}.m_max", 1e3, 1e15),
        sheet_centre=_choice(lo_d["sheet_centre"], SHEET_CENTRES, f"{k}.sheet_centre"),
    )
    if los.m_min >= los.m_max:
        raise SceneError(
            f"config key {k}.m_min = {los.m_min!r} must be < {k}.m_max = {los.m_max!r}"
        )
    return los


def _concentration_spec(c: Mapping[str, Any], k: str) -> ConcentrationSpec:
    mult = c["multipliers"]
    if not isinstance(mult, (list, tuple)) or not mult:
        raise SceneError(
            f"config key {k}.multipliers = {mult!r} must be a non-empty list of numbers > 0"
        )
    return ConcentrationSpec(
        multipliers=tuple(
            _real(a, f"{k}.multipliers[{i}]", 0.0, 1e3, lo_open=True) for i, a in enumerate(mult)
        ),
        scatter_dex=_real(c["scatter_dex"], f"{k}.scatter_dex", 0.0, 1.0),
        apply_to_los=_bool(c["apply_to_los"], f"{k}.apply_to_los"),
    )


def scenes_from_config(scenes: Mapping[str, Any] | None, key: str = "scenes") -> dict[str, Scene]:
    """All scenes of the config's ``scenes`` block; the five presets are always present."""
    scenes = dict(scenes or {})
    if not all(isinstance(v, Mapping) or v is None for v in scenes.values()):
        bad = [n for n, v in scenes.items() if not (isinstance(v, Mapping) or v is None)]
        raise SceneError(f"config key {key}.{bad[0]} must be a mapping")
    names = list(PRESETS) + [n for n in scenes if n not in PRESETS]
    return {n: Scene.from_config(n, scenes.get(n) or {}, f"{key}.{n}") for n in names}
