"""Tests of subslope.population: masked, chunked population sums and ragged packing."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from subslope.population import (
    choose_chunk_size,
    counts_to_offsets,
    negative_sheet_convergence,
    pack_ragged,
    pack_ragged_params,
    population_deflection,
    population_sum,
    sheet_deflector,
    unpack_ragged,
)


# --- small analytic profiles (test-local) -----------------------------------------
def pm_deflection(x, y, mass, cx, cy):
    """Point mass, theta_E^2 = mass: alpha = mass * d / |d|^2 (0/0 = NaN at the centre)."""
    dx, dy = x - cx, y - cy
    r2 = dx * dx + dy * dy
    return mass * dx / r2, mass * dy / r2


def sis_convergence(x, y, theta_e, cx, cy):
    r = torch.sqrt((x - cx) ** 2 + (y - cy) ** 2 + 1e-4)
    return theta_e / (2 * r)


def grid(n=12, dtype=torch.float64):
    v = (torch.arange(n, dtype=dtype) - (n - 1) / 2) * 0.3
    yy, xx = torch.meshgrid(v, v, indexing="ij")
    return xx.reshape(-1), yy.reshape(-1)


def random_population(rng, counts, dtype):
    counts = np.asarray(counts)
    m = counts.sum()
    flat = {
        "mass": rng.uniform(0.01, 0.1, m),
        "cx": rng.uniform(-1.7, 1.7, m) + 0.013,
        "cy": rng.uniform(-1.7, 1.7, m) + 0.017,
    }
    params, mask = pack_ragged_params(flat, counts=counts, dtype=dtype)
    return flat, params, mask


def loop_sum(flat, counts, x, y):
    """Reference: explicit python loop over systems and members."""
    out_x, out_y = [], []
    off = counts_to_offsets(counts)
    for b in range(len(counts)):
        ax = torch.zeros_like(x)
        ay = torch.zeros_like(y)
        for i in range(off[b], off[b + 1]):
            dx, dy = pm_deflection(x, y, *(torch.tensor(flat[k][i], dtype=x.dtype) for k in ("mass", "cx", "cy")))
            ax, ay = ax + dx, ay + dy
        out_x.append(ax)
        out_y.append(ay)
    return torch.stack(out_x), torch.stack(out_y)


def test_masked_sum_matches_loop(rng, dtype):
    counts = [5, 0, 13, 1]
    flat, params, mask = random_population(rng, counts, dtype)
    x, y = grid(dtype=dtype)
    ax, ay = population_deflection(pm_deflection, x, y, params, mask, chunk_size=4)
    rx, ry = loop_sum(flat, counts, x.double(), y.double())
    assert ax.shape == (4, x.numel()) and ax.dtype == dtype
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    torch.testing.assert_close(ax.double(), rx, rtol=tol, atol=tol)
    torch.testing.assert_close(ay.double(), ry, rtol=tol, atol=tol)
    assert torch.all(ax[1] == 0) and torch.all(ay[1] == 0)


def test_chunk_sizes_agree(rng):
    counts = [17, 3, 9]
    _, params, mask = random_population(rng, counts, torch.float64)
    x, y = grid()
    b = x[None].expand(3, -1)
    results = [population_deflection(pm_deflection, b, y[None].expand(3, -1), params, mask, chunk_size=c)
               for c in (1, 7, mask.shape[1], 1000)]
    results.append(population_deflection(pm_deflection, x, y, params, mask, max_elements=3 * 144 * 5))
    for ax, ay in results[1:]:
        torch.testing.assert_close(ax, results[0][0], rtol=1e-13, atol=1e-15)
        torch.testing.assert_close(ay, results[0][1], rtol=1e-13, atol=1e-15)


def test_padded_nan_does_not_leak(rng):
    """Padding that would give 0/0 (zero mass exactly on a pixel) or NaN parameters."""
    counts = [3, 1, 0]
    _, params, mask = random_population(rng, counts, torch.float64)
    x, y = grid()
    # padded slots: zero mass exactly at a pixel centre -> 0 * 0 / 0 = NaN if evaluated
    params["mass"] = torch.where(mask, params["mass"], torch.zeros(()))
    params["cx"] = torch.where(mask, params["cx"], x[0])
    params["cy"] = torch.where(mask, params["cy"], y[0])
    # sanity: the raw profile really produces NaN there
    assert torch.isnan(pm_deflection(x[0], y[0], torch.tensor(0.0), x[0], y[0])[0])
    for k in params:
        params[k].requires_grad_(True)
    ax, ay = population_deflection(pm_deflection, x, y, params, mask, chunk_size=2)
    assert torch.isfinite(ax).all() and torch.isfinite(ay).all()
    (ax.sum() + ay.sum()).backward()
    for k, v in params.items():
        assert torch.isfinite(v.grad).all(), k
        assert torch.all(v.grad[~mask] == 0), k
    # NaN-valued padding, all-padding system
    p2 = {k: torch.where(mask, v.detach(), torch.tensor(float("nan"))) for k, v in params.items()}
    ax2, ay2 = population_deflection(pm_deflection, x, y, p2, mask)
    torch.testing.assert_close(ax2, ax.detach())
    assert torch.all(ax2[2] == 0)


def test_all_padding_and_empty(dtype):
    x, y = grid(dtype=dtype)
    mask = torch.zeros((2, 3), dtype=torch.bool)
    params = {k: torch.full((2, 3), float("nan"), dtype=dtype) for k in ("mass", "cx", "cy")}
    ax, ay = population_deflection(pm_deflection, x, y, params, mask)
    assert ax.shape == (2, x.numel()) and torch.all(ax == 0) and torch.all(ay == 0)
    mask0 = torch.zeros((2, 0), dtype=torch.bool)
    params0 = {k: torch.zeros((2, 0), dtype=dtype) for k in ("mass", "cx", "cy")}
    ax, ay = population_deflection(pm_deflection, x, y, params0, mask0)
    assert ax.shape == (2, x.numel()) and ax.dtype == dtype and torch.all(ax == 0)
    k = population_sum(sis_convergence, x, y, {"theta_e": params0["mass"], "cx": params0["cx"],
                                               "cy": params0["cy"]}, mask0)
    assert isinstance(k, torch.Tensor) and k.shape == (2, x.numel())


def test_static_kwargs_and_scalar_output(rng):
    counts = [4, 2]
    flat, params, mask = random_population(rng, counts, torch.float64)
    x, y = grid()

    def scaled(x, y, mass, cx, cy, *, scale):
        return scale * pm_deflection(x, y, mass, cx, cy)[0]

    out = population_sum(scaled, x, y, params, mask, scale=2.0)
    ax, _ = population_deflection(pm_deflection, x, y, params, mask)
    torch.testing.assert_close(out, 2.0 * ax)


def test_bad_inputs_name_argument(rng):
    _, params, mask = random_population(rng, [2, 3], torch.float64)
    x, y = grid()
    with pytest.raises(ValueError, match="mask"):
        population_sum(sis_convergence, x, y, {}, mask.float())
    with pytest.raises(ValueError, match="params\\['mass'\\]"):
        population_deflection(pm_deflection, x, y, {**params, "mass": params["mass"][:, :1]}, mask)
    with pytest.raises(ValueError, match="chunk_size"):
        population_deflection(pm_deflection, x, y, params, mask, chunk_size=0)


def test_choose_chunk_size_bound():
    for b, n, p, me in [(8, 3000, 10000, 2**22), (1, 5, 10, 10**9), (64, 100, 40000, 1000)]:
        c = choose_chunk_size(b, n, p, me)
        assert 1 <= c <= n
        assert c == 1 or b * c * p <= me


def test_ragged_round_trip(rng):
    counts = np.array([3, 0, 5, 1])
    vals = rng.normal(size=counts.sum())
    padded, mask = pack_ragged(vals, counts=counts, fill=-7.0)
    assert padded.shape == (4, 5) and mask.sum() == counts.sum()
    assert np.all(padded[~mask] == -7.0)
    np.testing.assert_array_equal(padded[2, :5], vals[3:8])
    flat, c2 = unpack_ragged(padded, mask)
    np.testing.assert_array_equal(flat, vals)
    np.testing.assert_array_equal(c2, counts)
    p2, m2 = pack_ragged(vals, offsets=counts_to_offsets(counts), n_max=7)
    assert p2.shape == (4, 7)
    np.testing.assert_array_equal(unpack_ragged(torch.as_tensor(p2), torch.as_tensor(m2))[0], vals)
    vec = rng.normal(size=(counts.sum(), 2))  # vector-valued members
    pv, mv = pack_ragged(vec, counts=counts)
    np.testing.assert_array_equal(unpack_ragged(pv, mv)[0], vec)
    with pytest.raises(ValueError, match="counts"):
        pack_ragged(vals, counts=counts + 1)
    with pytest.raises(ValueError, match="offsets"):
        pack_ragged(vals, offsets=np.array([1, 2]))
    with pytest.raises(ValueError, match="values\\['a'\\]"):
        pack_ragged_params({"a": vals[:-1]}, counts=counts)


def test_negative_sheet_zero_mean(rng, dtype):
    counts = [6, 2, 0]
    m = sum(counts)
    flat = {"theta_e": rng.uniform(0.01, 0.2, m), "cx": rng.uniform(-2, 2, m), "cy": rng.uniform(-2, 2, m)}
    params, mask = pack_ragged_params(flat, counts=counts, dtype=dtype)
    x, y = grid(dtype=dtype)
    k_sheet = negative_sheet_convergence(sis_convergence, x, y, params, mask)
    assert k_sheet.shape == (3, 1) and k_sheet.dtype == dtype
    assert torch.all(k_sheet[:2] < 0) and k_sheet[2] == 0
    kappa = population_sum(sis_convergence, x, y, params, mask) + k_sheet
    tol = 1e-14 if dtype == torch.float64 else 1e-6
    assert kappa.mean(dim=-1).abs().max() < tol
    # the sheet deflector is the uniform-sheet deflection centred on the origin
    ax, ay = sheet_deflector(k_sheet[:, 0])(x[None], y[None])
    torch.testing.assert_close(ax, k_sheet * x[None])
    torch.testing.assert_close(ay, k_sheet * y[None])
