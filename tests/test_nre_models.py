"""ResNet ratio estimator: shapes, grid evaluation, stability, config round trip."""

from __future__ import annotations

import pytest
import torch

from subslope.nre.models import PRESETS, ResNetTrunk, build_model, count_parameters, model_card


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    m = build_model(
        {"depth": 10, "width": 0.0625, "head": [16, 16]}, gamma_mean=2.0, gamma_std=0.52
    )
    return m.eval()


def test_shapes_batched_and_unbatched(model):
    x = torch.randn(3, 100, 100)
    g = torch.tensor([1.2, 2.0, 2.8])
    with torch.no_grad():
        out = model(g, x)
        assert out.shape == (3,)
        assert torch.allclose(model(g, x[:, None]), out, atol=1e-6)  # (B, 1, H, W)
        assert model(g[0], x[0]).shape == ()  # one image, one γ
        assert torch.allclose(model(g[1], x[1]), out[1], atol=1e-5)
        assert model(2.0, x).shape == (3,)  # scalar γ broadcast over the batch
        stacked = model(torch.stack((g, g.flip(0))), x)  # (K, B) as the loss uses
        assert stacked.shape == (2, 3)
        assert torch.allclose(stacked[0], out, atol=1e-6)
    with pytest.raises(ValueError, match="shape"):
        model(g, torch.randn(2, 2, 2, 100, 100))


def test_log_ratio_grid_equals_loop(model):
    x = torch.randn(4, 100, 100)
    grid = torch.linspace(1.1, 2.9, 7)
    with torch.no_grad():
        table = model.log_ratio_grid(x, grid)
        loop = torch.stack([model(torch.full((4,), float(gv)), x) for gv in grid], dim=1)
        assert table.shape == (4, 7)
        assert torch.allclose(table, loop, atol=1e-5)
        assert torch.allclose(model.log_ratio_grid(x, grid, chunk=3), table, atol=1e-5)
        single = model.log_ratio_grid(x[2], grid)
        assert single.shape == (7,)
        assert torch.allclose(single, table[2], atol=1e-5)


def test_trunk_runs_once_in_grid(model, monkeypatch):
    calls = []
    orig = model.trunk.forward
    monkeypatch.setattr(model.trunk, "forward", lambda x: calls.append(x.shape[0]) or orig(x))
    with torch.no_grad():
        model.log_ratio_grid(torch.randn(5, 100, 100), torch.linspace(1.1, 2.9, 50))
    assert calls == [5]


@pytest.mark.parametrize("scale", [1e4, 1e8])
def test_logits_finite_for_extreme_inputs(model, scale):
    x = torch.randn(2, 100, 100) * scale
    x[0] = scale  # a flat, saturated image
    gammas = torch.tensor([1.1, 2.9, 1.0, 3.0])  # prior edges and just beyond
    with torch.no_grad():
        assert torch.isfinite(model.log_ratio_grid(x, gammas)).all()
    model.train()
    try:
        out = model(torch.tensor([1.1, 2.9]), x)
        out.sum().backward()
        assert torch.isfinite(out).all()
    finally:
        model.zero_grad(set_to_none=True)
        model.eval()


@pytest.mark.parametrize("stem,size", [("imagenet", 25), ("compact", 50), ("full", 100)])
def test_stems(stem, size):
    trunk = ResNetTrunk(depth=10, width=0.0625, stem=stem)
    assert trunk.stem(torch.zeros(1, 1, 100, 100)).shape[-1] == size
    assert trunk(torch.zeros(2, 1, 100, 100)).shape == (2, trunk.out_features)


def test_model_card_round_trip():
    m = build_model({"preset": "reduced"}, gamma_mean=2.0, gamma_std=0.5)
    card = model_card(m)
    assert 3e4 <= card["n_params"] <= 5e5  # "reduced": a few 1e5 parameters
    rebuilt = build_model(card["arch"], gamma_mean=card["gamma_mean"], gamma_std=card["gamma_std"])
    rebuilt.load_state_dict(m.state_dict())
    assert count_parameters(rebuilt) == card["n_params"]
    assert float(rebuilt.gamma_mean) == 2.0 and float(rebuilt.gamma_std) == 0.5
    x = torch.randn(2, 100, 100)
    with torch.no_grad():
        assert torch.equal(m.eval()(2.0, x), rebuilt.eval()(2.0, x))


def test_resnet50_builds_and_runs():
    m = build_model(PRESETS["resnet50"]).eval()
    assert 2.0e7 < count_parameters(m) < 2.6e7
    with torch.no_grad():
        assert m.log_ratio_grid(torch.randn(1, 100, 100), torch.tensor([1.5, 2.5])).shape == (1, 2)


@pytest.mark.parametrize(
    "arch,match",
    [
        ({"depth": 20}, "depth"),
        ({"stem": "big"}, "stem"),
        ({"width": 0}, "width"),
        ({"colour": 3}, "unknown"),
        ({"preset": "vit"}, "preset"),
    ],
)
def test_bad_arch(arch, match):
    with pytest.raises(ValueError, match=match):
        build_model(arch)
