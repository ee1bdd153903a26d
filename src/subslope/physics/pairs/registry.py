"""One entry per subhalo profile that a population pass can sum: its member table,
its pair function, the table row that is zero for padded members, the names of its
per-member parameters and their padding values.

The renderer (:mod:`subslope.render.populations`), the pair kernels
(:mod:`subslope.physics.pairs.sums`) and the scene validation read this registry, so a
new profile is one module with its table and pair plus one entry here (recipe in
``CONTRIBUTING.md``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

from subslope.physics.pairs.epl import epl_pair, epl_table
from subslope.physics.pairs.nfw import nfw_pair, nfw_table, tnfw_pair, tnfw_table

__all__ = ["PairProfile", "PAIR_PROFILES"]


@dataclass(frozen=True)
class PairProfile:
    """A profile of the population pass.

    table : ``(params, n_terms) -> (b, M, N)`` member table from ``(b, N)`` parameters.
    pair : ``(x, y, rows) -> (alpha_x, alpha_y, kappa)`` of members at points.
    amplitude_row : row of the table that is exactly zero for a padded member.
    keys : names of the per-member parameters (arrays of a population).
    padding : value of each parameter in a padded slot (zero amplitude).
    """

    table: Callable
    pair: Callable
    amplitude_row: int
    keys: tuple[str, ...]
    padding: Mapping[str, float]


PAIR_PROFILES: dict[str, PairProfile] = {
    "epl": PairProfile(
        epl_table,
        epl_pair,
        9,
        ("amp", "gamma", "e1", "e2", "x", "y"),
        {"amp": 0.0, "gamma": 2.0, "e1": 0.0, "e2": 0.0, "x": 0.0, "y": 0.0},
    ),
    "nfw": PairProfile(
        nfw_table,
        nfw_pair,
        3,
        ("r_s", "alpha_rs", "x", "y"),
        {"r_s": 1.0, "alpha_rs": 0.0, "x": 0.0, "y": 0.0},
    ),
    "tnfw": PairProfile(
        tnfw_table,
        tnfw_pair,
        3,
        ("r_s", "alpha_rs", "r_t", "x", "y"),
        {"r_s": 1.0, "alpha_rs": 0.0, "r_t": 1.0, "x": 0.0, "y": 0.0},
    ),
}
