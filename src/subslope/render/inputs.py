"""Checks of a render call's inputs: the macro keys of each component (a component is
on exactly when all its keys are present), the source given exactly once, and the sheet
centres."""

from __future__ import annotations

import numpy as np

from subslope.render.populations import SHEET_CENTRES

__all__ = ["GROUPS", "check_macro", "has_group", "multi_sersic_slots", "sheet_centre_pair"]

REQUIRED = (
    "z_lens",
    "z_source",
    "lens_x",
    "lens_y",
    "theta_e",
    "lens_e1",
    "lens_e2",
    "gamma_ml",
    "src_x",
    "src_y",
    "src_rotation",
)
GROUPS = {
    "multipoles": ("a3", "phi3", "a4", "phi4"),
    "shear": ("shear_g1", "shear_g2"),
    "lens_light": ("light_mag", "light_r", "light_n", "light_e1", "light_e2"),
    "source_sersic": ("src_mag", "src_r", "src_n", "src_e1", "src_e2"),
    "sky": ("sky_level",),
}


def multi_sersic_slots(macro: dict) -> int:
    """Number K of multi-Sérsic component slots in ``macro`` (0: not a multi-Sérsic source)."""
    if "src_ncomp" not in macro:
        return 0
    k = 0
    while f"src_frac_{k}" in macro:
        k += 1
    return k


MULTI_PER = ("frac", "r", "n", "e1", "e2", "dx", "dy")


def check_macro(macro: dict, sources) -> int:
    """The number of images B of ``macro``; a clear error for missing or partial keys."""
    missing = [k for k in REQUIRED if k not in macro]
    if missing:
        raise ValueError(
            f"macro is missing keys {missing} (see subslope.simulation.macro.sample_macro)"
        )
    n = len(np.asarray(macro["z_lens"]))
    for k, v in macro.items():
        if np.ndim(v) != 1 or len(v) != n:
            raise ValueError(f"macro[{k!r}] must be 1-D of length B = {n}, got shape {np.shape(v)}")
    for g, keys in GROUPS.items():
        have = [k in macro for k in keys]
        if any(have) and not all(have):
            raise ValueError(f"macro has only some of the {g} keys {keys}: give all or none")
    kmax = multi_sersic_slots(macro)
    if "src_ncomp" in macro or "src_mag_total" in macro:
        need = ["src_mag_total", "src_ncomp"] + [
            f"src_{p}_{j}" for j in range(max(kmax, 1)) for p in MULTI_PER
        ]
        missing = [kk for kk in need if kk not in macro]
        if missing:
            raise ValueError(
                f"multi-Sérsic source keys {missing} are missing from macro "
                "(see subslope.simulation.scenes.multi_sersic_keys)"
            )
        if "src_mag" in macro or sources is not None:
            raise ValueError(
                "give exactly one source: multi-Sérsic keys (src_mag_total, src_ncomp, ...), "
                "Sérsic keys (src_mag, ...) or sources="
            )
        return n
    sersic = "src_mag" in macro
    if sersic and sources is not None:
        raise ValueError(
            "give either Sérsic source keys (src_mag, ...) in macro or sources=, not both"
        )
    if not sersic and sources is None:
        raise ValueError(
            "no source: pass sources=PixelatedSources(...) or Sérsic keys src_mag, src_r, "
            "src_n, src_e1, src_e2 in macro"
        )
    return n


def has_group(macro: dict, group: str) -> bool:
    """True when ``macro`` carries the keys of component ``group``."""
    return GROUPS[group][0] in macro


def sheet_centre_pair(sheet_centre) -> tuple[str, str]:
    """``(subhalos, los)`` sheet centres from one name or a mapping with those keys."""
    if isinstance(sheet_centre, str):
        pair = (sheet_centre, sheet_centre)
    else:
        unknown = set(sheet_centre) - {"subhalos", "los"}
        if unknown:
            raise ValueError(
                f"sheet_centre keys must be 'subhalos' and 'los', got {sorted(unknown)}"
            )
        pair = (sheet_centre.get("subhalos", "origin"), sheet_centre.get("los", "origin"))
    for value in pair:
        if value not in SHEET_CENTRES:
            raise ValueError(f"sheet_centre must be one of {SHEET_CENTRES}, got {value!r}")
    return pair
