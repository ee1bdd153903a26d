"""The fast paths of the population passes against their references.

* :func:`subslope.physics.pairs.epl.power` (float32 bit arithmetic) against float64 ``**``
  over the full range the EPL pair uses (``R² ∈ [R_MIN², 10⁴]``, exponent ``−t/2 ∈
  [−1, 0]``), and its float64 path exactly ``exp(ex·log r2)``;
* :func:`subslope.physics.pairs.sums.direct_sums_few` (members outer) equals
  :func:`subslope.physics.pairs.sums.direct_sums` (members vectorised), eager and compiled;
* the main lens as a one-member table equals :func:`subslope.physics.profiles.epl.epl_deflection`;
* :func:`subslope.render.nearfar.near_pairs` equals a brute-force box-distance test;
* the γ classes of the split constants (:func:`subslope.render.nearfar.constant_class`).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.physics.pairs import epl as pair_epl
from subslope.physics.pairs import sums as PK
from subslope.physics.profiles.epl import R_MIN, epl_deflection
from subslope.render import nearfar as NF
from subslope.render import populations
from subslope.render import tiles as TL

pytestmark = pytest.mark.usefixtures("one_thread")
F64 = torch.float64


@pytest.mark.parametrize("ex", [-1.0, -0.95, -0.7, -0.5, -0.3, -0.05, -0.005, 0.0])
def test_power_float32_matches_float64(ex):
    r2 = torch.logspace(np.log10(R_MIN**2), 4, 40001, dtype=F64)
    ref = r2**ex
    got = pair_epl.power(r2.float(), torch.tensor(ex, dtype=torch.float32)).double()
    lib = torch.exp(ex * torch.log(r2.float())).double()
    rel = float(((got - ref) / ref).abs().max())
    rel_lib = float(((lib - ref) / ref).abs().max())
    assert torch.isfinite(got).all()
    # as accurate as the library float32 exp/log (whose error is the rounding of ex·ln r2)
    assert rel <= max(1.5 * rel_lib, 5e-7), (rel, rel_lib)


def test_power_float64_is_exp_log():
    r2 = torch.logspace(-18, 4, 101, dtype=F64)
    ex = torch.linspace(-1, 0, 101, dtype=F64)
    assert torch.equal(pair_epl.power(r2, ex), torch.exp(ex * torch.log(r2)))


def _epl_params(n, seed, dtype=F64, b=2):
    rng = np.random.default_rng(seed)
    vals = {
        "amp": rng.uniform(1e-5, 1e-3, (b, n)),
        "gamma": rng.uniform(1.05, 2.95, (b, n)),
        "e1": rng.uniform(-0.2, 0.2, (b, n)),
        "e2": rng.uniform(-0.2, 0.2, (b, n)),
        "x": rng.uniform(-2, 2, (b, n)),
        "y": rng.uniform(-2, 2, (b, n)),
    }
    return {k: torch.tensor(v, dtype=dtype) for k, v in vals.items()}


@pytest.mark.parametrize("n", [1, 2, 5, 31])
@pytest.mark.parametrize("compiled", [False, True])
def test_direct_sums_few_equals_direct_sums(n, compiled):
    table = PK.member_table("epl", _epl_params(n, seed=n), 8)
    g = torch.linspace(-2.5, 2.5, 37, dtype=F64)
    x, y = torch.meshgrid(g, g, indexing="xy")
    x, y = x.reshape(1, -1), y.reshape(1, -1)
    few = (
        torch.compile(PK.direct_sums_few, dynamic=True, fullgraph=True)
        if compiled
        else PK.direct_sums_few
    )
    a = few(x, y, table, "epl", True)
    b = PK.direct_sums(x, y, table, "epl", True)
    for u, v in zip(a, b):
        assert u.shape == v.shape == (2, x.shape[1])
        torch.testing.assert_close(u, v, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("dtype,tol", [(F64, 1e-12), (torch.float32, 2e-5)])
def test_main_lens_table_equals_epl_deflection(dtype, tol):
    p = {k: v[:, :1] for k, v in _epl_params(1, seed=3, dtype=dtype).items()}
    p["amp"] = torch.tensor([[1.2], [0.8]], dtype=dtype)
    g = torch.linspace(-2, 2, 41, dtype=dtype)
    x, y = torch.meshgrid(g, g, indexing="xy")
    x, y = x.reshape(1, -1), y.reshape(1, -1)
    table = pair_epl.epl_table(p, 14)
    ax, ay, _ = PK.direct_sums_few(x, y, table, "epl", False)
    rx, ry = epl_deflection(
        x, y, p["amp"], p["gamma"], p["e1"], p["e2"], p["x"], p["y"], n_terms=14
    )
    scale = float(torch.hypot(rx, ry).max())
    assert float((ax - rx).abs().max()) <= tol * scale
    assert float((ay - ry).abs().max()) <= tol * scale


def test_near_pairs_match_brute_force():
    rng = np.random.default_rng(0)
    b, n, nt, tile = 2, 60, 7, 8
    v = torch.tensor(rng.uniform(-10, 60, (b, n)), dtype=F64)
    u = torch.tensor(rng.uniform(-10, 60, (b, n)), dtype=F64)
    radius = torch.tensor(rng.uniform(0.5, 20, (b, n)), dtype=F64)
    live = torch.tensor(rng.uniform(size=(b, n)) < 0.8)
    tiles, mem = TL.near_pairs(v, u, radius, live, nt, tile)
    got = set(zip(tiles.tolist(), mem.tolist()))
    want = set()
    for k in range(b):
        for i in range(n):
            if not live[k, i]:
                continue
            for row in range(nt):
                for col in range(nt):
                    dv = max(
                        row * tile - 0.5 - float(v[k, i]),
                        float(v[k, i]) - (row * tile + tile - 0.5),
                        0.0,
                    )
                    du = max(
                        col * tile - 0.5 - float(u[k, i]),
                        float(u[k, i]) - (col * tile + tile - 0.5),
                        0.0,
                    )
                    if dv * dv + du * du <= float(radius[k, i]) ** 2:
                        want.add(((k * nt + row) * nt + col, k * n + i))
    assert got == want
    assert torch.all(tiles[1:] >= tiles[:-1])  # sorted by tile


def test_constant_classes_follow_gamma_edges():
    gam = torch.tensor([[1.01, 1.49, 1.5, 1.79, 2.0, 2.21, 2.49, 2.5, 2.99]], dtype=F64)
    p = {
        "amp": torch.ones_like(gam),
        "gamma": gam,
        "e1": torch.zeros_like(gam),
        "e2": torch.zeros_like(gam),
        "x": torch.zeros_like(gam),
        "y": torch.zeros_like(gam),
    }
    cls = NF.constant_class(PK.member_table("epl", p, 8), "epl")
    want = torch.bucketize(gam, torch.tensor(NF.EPL_GAMMA_EDGES, dtype=F64))
    assert torch.equal(cls, want)
    assert cls.min() == 0 and cls.max() == len(NF.EPL_GAMMA_EDGES)
    nfw = PK.member_table(
        "nfw",
        {
            "r_s": torch.ones(1, 3),
            "alpha_rs": torch.ones(1, 3),
            "x": torch.zeros(1, 3),
            "y": torch.zeros(1, 3),
        },
        0,
    )
    assert torch.equal(NF.constant_class(nfw, "nfw"), torch.zeros(1, 3, dtype=torch.long))
    for table in (NF.ERROR_CONSTANTS, NF.EDGE_ERROR_CONSTANTS):
        for profile, by_order in table.items():
            for _order, rows in by_order.items():
                assert len(rows) == (len(NF.EPL_GAMMA_EDGES) + 1 if profile == "epl" else 1)
                assert all(len(r) == len(NF.RHO_LADDER) for r in rows)


def test_member_rungs_rejects_unknown_order():
    table = PK.member_table("epl", _epl_params(3, seed=1), 8)
    with pytest.raises(ValueError, match="order 5"):
        NF.member_rungs(table, "epl", 0.1, 5, 1e-5)


def test_population_tables_name_a_missing_parameter():
    flat = {
        "amp": np.ones(2),
        "gamma": np.full(2, 2.0),
        "e1": np.zeros(2),
        "e2": np.zeros(2),
        "x": np.zeros(2),
    }
    with pytest.raises(ValueError, match="'y'"):
        populations.pack_population("epl", flat, np.array([2]), 8, F64, "cpu")
    with pytest.raises(ValueError, match="'y'"):
        populations.flat_table("epl", flat, 8, F64, "cpu")
